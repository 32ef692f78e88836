"""The simulated performer's looping gesture (``WavingMotion(loop_s=...)``, ``synth://imu?loop_s=``):
periodic in the loop phase, loops of jittered durations, a gyroscope that is the derivative of the
orientation it reports, deterministic whatever order it is asked in."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from capture.errors import ConfigError
from sim_devices.motion import WavingMotion
from sim_devices.synth import SynthTransport


def _times_at_phase(m: WavingMotion, target: np.ndarray) -> np.ndarray:
    """Solve phase(t) = target (Newton on the monotone phase, from the nominal guess)."""
    t = np.asarray(target, np.float64) * m.loop_s
    for _ in range(30):
        ph, rate = m.loop_phase(t)
        t = t - (ph - target) / rate
    return t


def test_synth_option_makes_a_looping_take():
    tr = SynthTransport("imu", {"loop_s": 1.2, "loop_jitter": 0.1, "seed": 4, "realtime": False})
    m = tr.motion
    assert m.loop_s == 1.2 and m.loop_jitter == 0.1
    bounds = m.loop_boundaries(12.0)
    d = np.diff(bounds)
    assert len(d) >= 8
    assert np.all((d >= 1.2 * 0.9 - 1e-12) & (d <= 1.2 * 1.1 + 1e-12))
    assert np.std(d) > 0.01  # the loops really differ in duration
    assert SynthTransport("imu", {"seed": 4}).motion.loop_s is None  # loop_s=0 (default): free waving


def test_the_angles_repeat_at_the_same_loop_phase_but_not_after_a_fixed_time():
    m = WavingMotion(3, loop_s=1.2)
    phase = np.linspace(0.05, 0.95, 37)
    _, _, e0 = m.at_many(_times_at_phase(m, phase))
    for k in (1, 2, 5, 9):
        tk = _times_at_phase(m, phase + k)
        np.testing.assert_allclose(m.loop_phase(tk)[0], phase + k, atol=1e-12)
        _, _, ek = m.at_many(tk)
        np.testing.assert_allclose(ek, e0, atol=1e-8)
    # the jitter is real: one nominal period later is not the same pose
    t = np.linspace(0.1, 1.1, 50)
    _, _, a = m.at_many(t)
    _, _, b = m.at_many(t + 5 * 1.2)
    assert np.max(np.abs(a - b)) > 1.0  # degrees


def test_the_phase_is_continuous_monotone_and_its_rate_is_its_derivative():
    m = WavingMotion(2, loop_s=1.2, loop_jitter=0.5)  # the largest jitter allowed
    t = np.linspace(-0.5, 30.0, 300_001)
    ph, rate = m.loop_phase(t)
    assert np.all(np.diff(ph) > 0) and np.all(rate > 0)
    bounds = m.loop_boundaries(30.0)
    np.testing.assert_allclose(m.loop_phase(bounds)[0], np.arange(len(bounds)), atol=1e-12)
    h = t[1] - t[0]
    # (central differences are off by O(h) only where the second derivative steps: at the boundaries)
    np.testing.assert_allclose((ph[2:] - ph[:-2]) / (2 * h), rate[1:-1], rtol=1e-4)
    # the rate is continuous across loop boundaries (no jump in the angular rate there)
    eps = 1e-9
    left, right = m.loop_phase(bounds[1:] - eps)[1], m.loop_phase(bounds[1:] + eps)[1]
    np.testing.assert_allclose(left, right, rtol=1e-6)


def test_the_gyro_is_the_derivative_of_the_reported_orientation():
    """Body rate from the orientation alone: R(t-h)^T R(t+h) = exp(2h [w]x), independent of the
    Euler-rate formula the generator uses."""
    m = WavingMotion(1, loop_s=1.2)
    t = np.linspace(0.0, 10.0, 4001)  # crosses about 8 loop boundaries
    h = 1e-5
    _, gyro, _ = m.at_many(t)
    _, _, e_minus = m.at_many(t - h)
    _, _, e_plus = m.at_many(t + h)
    # roll, pitch, yaw (ZYX): R = Rz(yaw) Ry(pitch) Rx(roll)
    r_minus = Rotation.from_euler("ZYX", e_minus[:, ::-1], degrees=True)
    r_plus = Rotation.from_euler("ZYX", e_plus[:, ::-1], degrees=True)
    w = np.degrees((r_minus.inv() * r_plus).as_rotvec() / (2 * h))
    np.testing.assert_allclose(gyro, w, atol=1e-3 * np.max(np.abs(gyro)))
    assert np.max(np.abs(gyro)) > 50.0  # deg/s: a real gesture, not a still sensor


def test_gravity_in_the_accelerometer_follows_the_orientation():
    m = WavingMotion(5, loop_s=0.9)
    t = np.linspace(0.0, 6.0, 601)
    acc, _, eul = m.at_many(t)
    r = Rotation.from_euler("ZYX", eul[:, ::-1], degrees=True)
    # specific force = R^T (a + g z); averaged over whole loops the linear part cancels
    g_body = r.inv().apply(np.array([0.0, 0.0, 1.0]))
    lin = acc - g_body
    assert np.max(np.abs(lin)) < 1.0 / 9.80665 * 1.01 * np.sqrt(3)  # at most the 1 m/s^2 lin terms
    assert np.max(np.linalg.norm(lin, axis=1)) > 0.005


def test_deterministic_whatever_the_query_order():
    t = np.arange(0.0, 20.0, 1 / 200)
    whole = WavingMotion(7, loop_s=1.3).at_many(t)
    m = WavingMotion(7, loop_s=1.3)
    blocks = [t[i:i + 20] for i in range(0, t.size, 20)]
    late_first = [m.at_many(b) for b in reversed(blocks)][::-1]
    for a, b in zip(whole, (np.concatenate(x) for x in zip(*late_first, strict=True)), strict=True):
        assert np.array_equal(a, b)
    other = WavingMotion(8, loop_s=1.3).at_many(t)
    assert not np.allclose(whole[2], other[2])


def test_mean_loop_duration_is_the_span_over_the_loops_it_covers():
    m = WavingMotion(2, loop_s=1.2)
    b = m.loop_boundaries(10.0)
    assert m.mean_loop_s(b[1], b[6]) == pytest.approx((b[6] - b[1]) / 5, rel=1e-12)
    assert 1.2 * 0.92 <= m.mean_loop_s(0.0, 10.0) <= 1.2 * 1.08


@pytest.mark.parametrize("kw", [{"loop_s": -1.0}, {"loop_s": float("nan")}, {"loop_s": 1.0, "loop_jitter": 0.6}])
def test_bad_loop_options_are_refused(kw):
    with pytest.raises(ValueError):
        WavingMotion(1, **kw)


def test_bad_synth_loop_option_is_one_config_error():
    with pytest.raises(ConfigError, match="loop_jitter"):
        SynthTransport("imu", {"loop_s": 1.2, "loop_jitter": 0.9})
