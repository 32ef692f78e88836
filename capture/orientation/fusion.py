"""The x-io Fusion backend (the ``imufusion`` library): :class:`FusionBackend` runs imufusion's
``Ahrs`` in the ENU convention, optionally with its ``Bias`` gyro-offset learner, with acceleration
and magnetic rejection and a rejection-free grace after every (re)initialisation, over a batch of
prepared samples (the one-sample path on plain floats is
:meth:`capture.orientation.filter.OrientationFilter.update_one`)."""

from __future__ import annotations

import math
from typing import TYPE_CHECKING, Any, cast

import numpy as np

from capture.calibration import G0
from capture.errors import ConfigError
from capture.orientation.base import (
    FLAG_ACC_IGNORED,
    FLAG_ACC_RECOVERY,
    FLAG_MAG_IGNORED,
    FLAG_MAG_RECOVERY,
    FLAG_OVERRANGE,
    Backend,
)

if TYPE_CHECKING:
    from capture.orientation.base import StepOutputs, Steps

_R2D = 180.0 / math.pi
_INV_G0 = 1.0 / G0


class FusionBackend(Backend):
    """imufusion's ``Ahrs`` (and ``Bias`` with ``gyro_offset``), fed deg/s and g.

    Pitfalls handled here (measured; see the tests):

    * ``imufusion`` 1.3.3 ignores the ``convention`` keyword of ``AhrsSettings(...)`` (it stays NWU);
      settings are assigned one by one and read back.
    * After every (re)initialisation Fusion runs ``init_grace_s`` (1 s) without rejection and with a
      gain of at least ``init_gain`` (2), or one accelerometer reading taken in motion could leave it
      rejecting the accelerometer until its recovery timeout (measured on a reconnecting simulated
      WitMotion: 54 deg median roll/pitch error before, 2 deg after).
    """

    def __init__(self, s: dict[str, Any]) -> None:
        super().__init__(s)
        import imufusion

        self._imf = imufusion
        self.ahrs = imufusion.Ahrs()
        self.rate = float(s["nominal_rate_hz"] or 100.0)
        self.grace_left = 0.0  # seconds of rejection-free updates left after an (re)initialisation
        self._apply_settings()
        self.offset: imufusion.Bias | None = None
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
        """Use ``rate`` (Hz) as Fusion's sample rate (its startup ramp and rejection timeout)."""
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

    def run(self, steps: Steps, out: StepOutputs) -> None:
        ahrs = self.ahrs
        setp = ahrs.set_sample_period
        upd = ahrs.update
        upd_nm = ahrs.update_no_magnetometer
        getq = ahrs.get_quaternion
        gets = ahrs.get_internal_states
        getf = ahrs.get_flags
        off = self.offset.update if self.offset is not None else None
        dt, gyro, acc, mag, use_mag, mode, q_before = steps
        gd = gyro * _R2D
        ag = acc * _INV_G0
        acc_ok = cast("np.ndarray", np.isfinite(ag).all(axis=1))  # (n, 3) in: an array, never numpy's scalar
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
        m_rows: list[np.ndarray] = list(mag) if any(ums) else []
        qs: list[Any] = [None] * n
        ae = [nan] * n
        me = [nan] * n
        fs = [0] * n
        for i in range(n):
            if modes[i]:
                qs[i] = self.restart(steps, i, np.array(qs[i - 1], np.float64) if i else q_before)
                continue
            g = g_rows[i]
            if off is not None:
                g = off(g)
            setp(dts[i])
            if ums[i]:
                upd(g, a_rows[i], m_rows[i])
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
        q_out, flags, acc_err, mag_err = out
        q_out[:] = qs
        acc_err[:] = ae
        mag_err[:] = me
        flags |= np.array(fs, np.uint16)
