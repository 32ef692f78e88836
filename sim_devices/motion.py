"""A seeded generator of plausible hand-held motion: smooth multi-sine orientation (a performer
waving a wrist rig at 0.2-2 Hz) plus small linear acceleration, giving the angular rate and the
specific force an IMU strapped to it would measure.

With ``loop_s`` the performer repeats one gesture instead (the ground truth for cycle extraction in
the demo): the orientation and linear acceleration are smooth harmonic functions of a loop phase
that advances by one per loop, each loop lasting ``loop_s`` times a seeded factor in
``[1 - loop_jitter, 1 + loop_jitter]``. The phase is a monotone cubic Hermite curve through the loop
boundaries (continuous, with a continuous rate), and the angular rate is computed from the phase rate,
so the gyroscope stays the exact derivative of the orientation.
"""

from __future__ import annotations

import math
import random

import numpy as np

G = 9.80665

LOOP_HARMONICS = 3


class WavingMotion:
    """Deterministic for a given seed; ``at_many(t)`` for any times in seconds.

    Args:
        seed: motion seed.
        amplitude_deg: scale of the roll and yaw swing (pitch swings half as far).
        loop_s: mean duration of one loop of a repeated gesture (seconds), or None for free waving.
        loop_jitter: each loop lasts ``loop_s * U[1 - loop_jitter, 1 + loop_jitter]`` (0 to 0.5).

    Raises:
        ValueError: ``loop_s`` is not a positive finite number or ``loop_jitter`` is outside 0..0.5.
    """

    def __init__(self, seed: int = 1, amplitude_deg: float = 40.0, *, loop_s: float | None = None,
                 loop_jitter: float = 0.08) -> None:
        rnd = random.Random(seed)
        self.terms: list[list[tuple[float, float, float]]] = []
        for axis in range(3):
            amp = math.radians(amplitude_deg) * (0.5 if axis == 1 else 1.0)
            terms = []
            for _ in range(3):
                terms.append((amp * rnd.uniform(0.2, 0.5), 2 * math.pi * rnd.uniform(0.2, 2.0),
                              rnd.uniform(0, 2 * math.pi)))
            self.terms.append(terms)
        self.lin = [(rnd.uniform(0.2, 1.0), 2 * math.pi * rnd.uniform(0.5, 1.5), rnd.uniform(0, 2 * math.pi))
                    for _ in range(3)]
        self.loop_s = loop_s
        self.loop_jitter = loop_jitter
        if loop_s is None:
            return
        if not (math.isfinite(loop_s) and loop_s > 0):
            raise ValueError(f"loop_s must be a positive number of seconds, not {loop_s}")
        if not 0.0 <= loop_jitter <= 0.5:
            raise ValueError(f"loop_jitter must be in 0..0.5, not {loop_jitter}")
        # A separate generator, so that the free waving above is drawn exactly as without loops.
        lrnd = random.Random(seed * 1_000_003 + 17)
        # per axis, harmonic h = 1..LOOP_HARMONICS of the loop: (amplitude rad, h, phase)
        self.loop_terms = []
        for axis in range(3):
            amp = math.radians(amplitude_deg) * (0.5 if axis == 1 else 1.0)
            self.loop_terms.append([(amp * lrnd.uniform(0.3, 0.6) / h, h, lrnd.uniform(0, 2 * math.pi))
                                    for h in range(1, LOOP_HARMONICS + 1)])
        self.loop_lin = [(lrnd.uniform(0.2, 1.0), axis + 1, lrnd.uniform(0, 2 * math.pi)) for axis in range(3)]
        self._loop_rnd = random.Random(seed * 1_000_003 + 29)
        self._bounds = [0.0]  # loop k runs from _bounds[k] to _bounds[k + 1] (seconds)

    # ------------------------------------------------------------------------------------- loops
    def _extend(self, until_s: float) -> None:
        """Draw loop durations (in order, so any query order gives the same loops) until ``until_s``
        lies inside a loop that has a loop after it."""
        assert self.loop_s is not None
        b = self._bounds
        while len(b) < 3 or b[-2] <= until_s:
            b.append(b[-1] + self.loop_s * self._loop_rnd.uniform(1.0 - self.loop_jitter, 1.0 + self.loop_jitter))

    def loop_boundaries(self, until_s: float) -> np.ndarray:
        """The start times (s) of the loops that begin at or before ``until_s`` (the first is 0).

        Raises:
            ValueError: the motion has no loops (``loop_s`` is None).
        """
        if self.loop_s is None:
            raise ValueError("this motion does not loop (loop_s is None)")
        self._extend(until_s)
        return np.array([x for x in self._bounds if x <= until_s])

    def loop_phase(self, t: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """The loop phase (loops since t = 0) and its rate (loops per second) at times ``t`` (s).

        Between two boundaries the phase is a cubic Hermite curve from k to k + 1 whose slope at each
        boundary is the mean of the adjacent loops' rates (monotone for jitter up to 0.5). Before 0 it
        runs on at the first loop's rate.

        Raises:
            ValueError: the motion has no loops (``loop_s`` is None).
        """
        if self.loop_s is None:
            raise ValueError("this motion does not loop (loop_s is None)")
        t = np.asarray(t, np.float64)
        if t.size:
            self._extend(float(np.max(t)))
        b = np.asarray(self._bounds)
        d = np.diff(b)
        slope = np.empty(b.size - 1)  # at each boundary except the last
        slope[0] = 1.0 / d[0]
        slope[1:] = 0.5 * (1.0 / d[:-1] + 1.0 / d[1:])
        k = np.clip(np.searchsorted(b, t, side="right") - 1, 0, b.size - 3)
        dk = d[k]
        s = (t - b[k]) / dk
        m0, m1 = slope[k] * dk, slope[k + 1] * dk  # slopes in loops per unit s
        s2, s3 = s * s, s * s * s
        phase = k + (-2 * s3 + 3 * s2) + m0 * (s3 - 2 * s2 + s) + m1 * (s3 - s2)
        rate = ((-6 * s2 + 6 * s) + m0 * (3 * s2 - 4 * s + 1) + m1 * (3 * s2 - 2 * s)) / dk
        before = t < 0
        if np.any(before):
            phase = np.where(before, t * slope[0], phase)
            rate = np.where(before, slope[0], rate)
        return phase, rate

    def mean_loop_s(self, d0: float, d1: float) -> float:
        """The mean loop duration over motion seconds ``[d0, d1]`` (s): its length over the loops it
        spans, partial loops counted by their phase (the period a cycle extractor should find there).
        This is ``devices.transports.base.LoopingMotion``.

        Raises:
            ValueError: the motion has no loops, or ``d1 <= d0``.
        """
        if not d1 > d0:
            raise ValueError("d1 must be after d0")
        ph, _ = self.loop_phase(np.array([d0, d1]))
        return float((d1 - d0) / (ph[1] - ph[0]))

    def _loop_angles(self, t: np.ndarray) -> tuple[np.ndarray, np.ndarray, tuple[np.ndarray, ...]]:
        phase, prate = self.loop_phase(t)
        ang = np.zeros((3, t.size))
        rate = np.zeros((3, t.size))
        for k, terms in enumerate(self.loop_terms):
            for amp, h, ph in terms:
                x = 2 * math.pi * h * phase + ph
                ang[k] += amp * np.sin(x)
                rate[k] += amp * 2 * math.pi * h * np.cos(x)
        rate *= prate  # d/dt = d/dphase * dphase/dt
        lin = tuple(amp * np.sin(2 * math.pi * h * phase + ph) for amp, h, ph in self.loop_lin)
        return ang, rate, lin

    # ------------------------------------------------------------------------------------ motion
    def at_many(self, t: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """The motion at times ``t`` (s): specific force in the sensor frame (g, (n,3)), body angular
        rate (deg/s, (n,3)) and roll, pitch, yaw (ZYX, degrees, (n,3))."""
        t = np.asarray(t, np.float64)
        if self.loop_s is not None:
            ang, rate, (ax, ay, az) = self._loop_angles(t)
        else:
            ang = np.zeros((3, t.size))
            rate = np.zeros((3, t.size))
            for k, terms in enumerate(self.terms):
                for amp, w, ph in terms:
                    ang[k] += amp * np.sin(w * t + ph)
                    rate[k] += amp * w * np.cos(w * t + ph)
            ax, ay, az = (amp * np.sin(w * t + ph) for amp, w, ph in self.lin)
        return imu_readings(ang, rate, (ax, ay, az))


def imu_readings(ang: np.ndarray, rate: np.ndarray, lin: tuple[np.ndarray, ...]) -> tuple[np.ndarray, np.ndarray,
                                                                                       np.ndarray]:
    """What an IMU reads on a body with ZYX angles ``ang = (roll, pitch, yaw)`` (rad, ``(3, n)``), their
    rates (rad/s) and linear acceleration ``lin`` (world x, y, z, m/s^2; z up): specific force in the
    sensor frame (g, ``(n, 3)``), body angular rate (deg/s, ``(n, 3)``), angles (degrees, ``(n, 3)``)."""
    ax, ay, az = lin
    phi, theta, psi = ang
    dphi, dtheta, dpsi = rate
    sphi, cphi = np.sin(phi), np.cos(phi)
    sth, cth = np.sin(theta), np.cos(theta)
    sps, cps = np.sin(psi), np.cos(psi)
    p = dphi - dpsi * sth
    q = dtheta * cphi + dpsi * cth * sphi
    r = -dtheta * sphi + dpsi * cth * cphi
    az = az + G
    r00, r01, r02 = cps * cth, cps * sth * sphi - sps * cphi, cps * sth * cphi + sps * sphi
    r10, r11, r12 = sps * cth, sps * sth * sphi + cps * cphi, sps * sth * cphi - cps * sphi
    r20, r21, r22 = -sth, cth * sphi, cth * cphi
    acc = np.stack([r00 * ax + r10 * ay + r20 * az, r01 * ax + r11 * ay + r21 * az,
                    r02 * ax + r12 * ay + r22 * az], axis=1) / G
    gyro = np.degrees(np.stack([p, q, r], axis=1))
    eul = np.degrees(np.stack([phi, theta, psi], axis=1))
    return acc, gyro, eul


class PuppeteerMotion:
    """A puppeteer's phone, held at the wrist and pointed at a character standing ``reach`` metres in front
    and ``drop`` metres below it (the default ``retarget.puppet`` geometry): a choreography of
    ``PERIOD_S`` seconds, repeated. Turning the phone about the vertical sweeps the character round the
    performer (speed = ``reach`` x turn rate); rolling it lifts or lowers the stick's end.

    0-0.6 s still (idle); walk (1.3 m/s) to 1.9 s; run (3 m/s) to 3.0 s; slow to a stop by 3.3 s; a clean
    ballistic hop of the stick's end (take-off 2.2 m/s) at 3.5 s; a crouched walk (the end 0.3 m
    lower) from 4.3 s; standing and still again before the period ends. The phone starts level with
    yaw 0; ``at_many`` has ``WavingMotion``'s outputs, so the same page and app simulators send it.

    Args:
        reach: horizontal distance from the phone to the character's hips (m).
        drop: how far the hips are below the phone (m).
    """

    PERIOD_S = 7.0
    _OMEGA = ((0.0, 0.0), (0.6, 0.0), (0.8, 0.87), (1.9, 0.87), (2.1, 2.0), (3.0, 2.0), (3.3, 0.0), (4.3, 0.0),
              (4.6, 0.6), (6.0, 0.6), (6.3, 0.0), (7.0, 0.0))           # turn rate keyframes (s, rad/s)
    _HOP = (3.5, 2.2)                                                    # take-off (s), speed (m/s)
    _CROUCH = ((4.1, 0.0), (4.4, -0.3), (6.2, -0.3), (6.6, 0.0))         # end height offset keyframes (s, m)

    def __init__(self, reach: float = 1.5, drop: float = 0.32) -> None:
        if not (reach > 0 and drop >= 0 and math.isfinite(reach) and math.isfinite(drop)):
            raise ValueError("reach must be positive and drop non-negative")
        self.reach, self.drop = float(reach), float(drop)
        # the yaw is the integral of the piecewise-linear turn rate: exact on a fine grid, then interpolated
        self._grid = np.linspace(0.0, self.PERIOD_S, 7001)
        kt, kw = np.array(self._OMEGA).T
        w = np.interp(self._grid, kt, kw)
        self._w = w
        self._yaw = np.concatenate([[0.0], np.cumsum(0.5 * (w[1:] + w[:-1]) * np.diff(self._grid))])

    def height_offset(self, t: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """The stick end's height above its start (m) and its rate (m/s) at times ``t`` (s)."""
        u = np.mod(np.asarray(t, np.float64), self.PERIOD_S)
        kt, kh = np.array(self._CROUCH).T
        h = np.interp(u, kt, kh)
        seg = np.searchsorted(kt, u, side="right") - 1
        inside = (seg >= 0) & (seg < kt.size - 1)
        dh = np.where(inside, (np.diff(kh) / np.diff(kt))[np.clip(seg, 0, kt.size - 2)], 0.0)
        t0, v0 = self._HOP
        tau = u - t0
        flight = 2.0 * v0 / G
        up = (tau >= 0) & (tau <= flight)
        h = h + np.where(up, v0 * tau - 0.5 * G * tau * tau, 0.0)
        dh = dh + np.where(up, v0 - G * tau, 0.0)
        return h, dh

    def at_many(self, t: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """As ``WavingMotion.at_many``: specific force (g), body rate (deg/s), roll/pitch/yaw (deg)."""
        t = np.asarray(t, np.float64)
        loops, u = np.divmod(t, self.PERIOD_S)
        psi = loops * self._yaw[-1] + np.interp(u, self._grid, self._yaw)
        dpsi = np.interp(u, self._grid, self._w)
        # roll alpha lifts the end by h: D sin(-alpha) - H cos(alpha) + H = h  (D = reach, H = drop)
        h, dh = self.height_offset(t)
        r = math.hypot(self.reach, self.drop)
        beta = math.atan2(self.drop, self.reach)
        x = np.clip((self.drop - h) / r, -1.0, 1.0)
        phi = np.arcsin(x) - beta
        dphi = -dh / (r * np.sqrt(np.maximum(1.0 - x * x, 1e-12)))
        zero = np.zeros_like(t)
        return imu_readings(np.stack([phi, zero, psi]), np.stack([dphi, zero, dpsi]), (zero, zero, zero))


#: The motions a simulated phone can perform, by name (``perfcap sim phone --motion``).
PHONE_MOTIONS = ("waving", "puppeteer")


def phone_motion(name: str, seed: int = 1) -> WavingMotion | PuppeteerMotion:
    """The named phone motion: ``waving`` (seeded free waving) or ``puppeteer`` (the puppet choreography).

    Raises:
        ValueError: an unknown name.
    """
    if name == "waving":
        return WavingMotion(seed)
    if name == "puppeteer":
        return PuppeteerMotion()
    raise ValueError(f"unknown phone motion {name!r}: expected one of {', '.join(PHONE_MOTIONS)}")
