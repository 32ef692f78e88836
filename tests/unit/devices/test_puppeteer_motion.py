"""The simulated puppeteer (``PuppeteerMotion``, ``perfcap sim phone --motion puppeteer``): an IMU-only
phone whose choreography, read as the page's attitude through the real conversion, drives the default
puppet through idle, walk, run, a clean hop and a crouched walk with no fall."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from capture.app.puppet_input import attitude_quaternions
from capture.sample import DeviceIdentity, StreamInfo
from retarget.puppet import PhoneInput, PuppetRetargeter
from retarget.states import PuppetState as S
from sim_devices.motion import PHONE_MOTIONS, G, PuppeteerMotion, WavingMotion, phone_motion

ATTITUDE = StreamInfo("ph/attitude", "euler", ("alpha", "beta", "gamma"), ("deg",) * 3, None,
                      DeviceIdentity("phone", "ph"))


def page_quaternions(m: PuppeteerMotion, t: np.ndarray) -> np.ndarray:
    _, _, eul = m.at_many(t)                     # roll, pitch, yaw: the page sends alpha=yaw, beta=roll, gamma=pitch
    return attitude_quaternions(ATTITUDE, np.stack([eul[:, 2], eul[:, 0], eul[:, 1]], axis=1))


def test_the_gyro_is_the_derivative_of_the_attitude_and_the_phone_only_rotates():
    m = PuppeteerMotion()
    t = np.arange(0.0, 2 * m.PERIOD_S, 0.002)
    acc, gyro, eul = m.at_many(t)
    r = Rotation.from_euler("ZYX", eul[:, ::-1], degrees=True)
    body_rate = (r[:-1].inv() * r[1:]).as_rotvec() / np.diff(t)[:, None]
    mid = 0.5 * (gyro[:-1] + gyro[1:])
    smooth = np.abs(np.diff(gyro, axis=0)).max(axis=1) < 5.0   # not at the hop's take-off and landing kinks
    assert smooth.mean() > 0.99
    np.testing.assert_allclose(np.degrees(body_rate)[smooth], mid[smooth], atol=0.5)
    # no linear acceleration: the accelerometer reads gravity only (1 g)
    np.testing.assert_allclose(np.linalg.norm(acc, axis=1), 1.0, atol=1e-9)


def test_the_stick_end_sweeps_a_circle_and_hops_on_a_ballistic_arc():
    m = PuppeteerMotion(reach=1.5, drop=0.32)
    t = np.arange(0.0, m.PERIOD_S, 1 / 240)
    q = page_quaternions(m, t)
    r = Rotation.from_quat(q[:, [1, 2, 3, 0]])
    rel = r * r[0].inv()                          # the stick turns with the phone about the pivot
    end = rel.apply([0.0, -0.32, 1.5])
    np.testing.assert_allclose(np.hypot(end[:, 0], end[:, 2])[t < 3.4], 1.5, atol=1e-9)
    hop = (t >= 3.5) & (t <= 3.5 + 2 * 2.2 / G)
    tau = t[hop] - 3.5
    np.testing.assert_allclose(end[hop, 1] + 0.32, 2.2 * tau - 0.5 * G * tau ** 2, atol=1e-9)
    crouch = (t > 4.5) & (t < 6.1)
    np.testing.assert_allclose(end[crouch, 1] + 0.32, -0.3, atol=1e-9)


def test_the_choreography_drives_the_puppet_without_a_fall():
    m = PuppeteerMotion()
    t = np.arange(0.0, m.PERIOD_S, 1 / 60)
    p = PuppetRetargeter()
    frames = [p.step(PhoneInput(float(ti), tuple(qi), True)) for ti, qi in zip(t, page_quaternions(m, t), strict=True)]
    states = [f.state for f in frames]
    tl = [s for k, s in enumerate(states) if k == 0 or s is not states[k - 1]]
    assert tl == [S.LOCOMOTION, S.JUMP_ANTICIPATION, S.AIRBORNE, S.LANDING, S.LOCOMOTION]
    root = np.array([f.root_pos for f in frames])
    speed = np.hypot(np.diff(root[:, 0]), np.diff(root[:, 2])) * 60.0

    def mean(a: float, b: float) -> float:
        return float(speed[(t[1:] > a) & (t[1:] < b)].mean())

    assert mean(0.0, 0.5) < 0.05                              # idle
    assert mean(1.3, 1.9) == pytest.approx(1.3, abs=0.25)      # walk (catching up with the end)
    assert mean(2.5, 3.0) == pytest.approx(3.0, abs=0.3)       # run
    crouched = [f.blend[1] for f, ti in zip(frames, t, strict=True) if 5.0 < ti < 6.0]
    assert max(crouched) < 0.4                                 # the crouched walk
    assert frames[-1].blend[1] > 0.9 and speed[-10:].max() < 0.1


def test_phone_motions_by_name():
    assert PHONE_MOTIONS == ("waving", "puppeteer")
    assert isinstance(phone_motion("waving", 3), WavingMotion)
    assert isinstance(phone_motion("puppeteer"), PuppeteerMotion)
    with pytest.raises(ValueError, match="unknown phone motion 'wave'"):
        phone_motion("wave")
    with pytest.raises(ValueError, match="reach"):
        PuppeteerMotion(reach=0.0)
