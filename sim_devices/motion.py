"""A seeded generator of plausible hand-held motion: smooth multi-sine orientation (a performer
waving a wrist rig at 0.2-2 Hz) plus small linear acceleration, giving the angular rate and the
specific force an IMU strapped to it would measure."""

from __future__ import annotations

import math
import random

import numpy as np

G = 9.80665


class WavingMotion:
    """Deterministic for a given seed; ``at_many(t)`` for any times in seconds."""

    def __init__(self, seed: int = 1, amplitude_deg: float = 40.0) -> None:
        rnd = random.Random(seed)
        self.terms: list[list[tuple[float, float, float]]] = []
        for axis in range(3):
            amp = math.radians(amplitude_deg) * (0.5 if axis == 1 else 1.0)
            terms = []
            for _ in range(3):
                terms.append((amp * rnd.uniform(0.2, 0.5), 2 * math.pi * rnd.uniform(0.2, 2.0), rnd.uniform(0, 2 * math.pi)))
            self.terms.append(terms)
        self.lin = [(rnd.uniform(0.2, 1.0), 2 * math.pi * rnd.uniform(0.5, 1.5), rnd.uniform(0, 2 * math.pi)) for _ in range(3)]

    def at_many(self, t: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """The motion at times ``t`` (s): specific force in the sensor frame (g, (n,3)), body angular
        rate (deg/s, (n,3)) and roll, pitch, yaw (ZYX, degrees, (n,3))."""
        t = np.asarray(t, np.float64)
        ang = np.zeros((3, t.size))
        rate = np.zeros((3, t.size))
        for k, terms in enumerate(self.terms):
            for amp, w, ph in terms:
                ang[k] += amp * np.sin(w * t + ph)
                rate[k] += amp * w * np.cos(w * t + ph)
        phi, theta, psi = ang
        dphi, dtheta, dpsi = rate
        sphi, cphi = np.sin(phi), np.cos(phi)
        sth, cth = np.sin(theta), np.cos(theta)
        sps, cps = np.sin(psi), np.cos(psi)
        p = dphi - dpsi * sth
        q = dtheta * cphi + dpsi * cth * sphi
        r = -dtheta * sphi + dpsi * cth * cphi
        ax, ay, az = (amp * np.sin(w * t + ph) for amp, w, ph in self.lin)
        az = az + G
        r00, r01, r02 = cps * cth, cps * sth * sphi - sps * cphi, cps * sth * cphi + sps * sphi
        r10, r11, r12 = sps * cth, sps * sth * sphi + cps * cphi, sps * sth * cphi - cps * sphi
        r20, r21, r22 = -sth, cth * sphi, cth * cphi
        acc = np.stack([r00 * ax + r10 * ay + r20 * az, r01 * ax + r11 * ay + r21 * az,
                        r02 * ax + r12 * ay + r22 * az], axis=1) / G
        gyro = np.degrees(np.stack([p, q, r], axis=1))
        eul = np.degrees(np.stack([phi, theta, psi], axis=1))
        return acc, gyro, eul
