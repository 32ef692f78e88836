"""IMU calibration: the record and its JSON, resets, still-period bias, automatic bias (not fooled by slow
rotation), accelerometer and magnetometer fits on synthetic data with known answers and on real data."""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from capture.calibration import (
    FORMAT_VERSION,
    G0,
    GyroBiasEstimator,
    ImuCalibration,
    estimate_gyro_bias,
    fit_accelerometer,
    fit_magnetometer,
    mounting_from_gravity,
    quat_heading,
    still_bias,
    still_mask,
    still_poses,
    still_segments,
)
from capture.errors import ConfigError
from capture.quat import quat_rotate

D2R = math.pi / 180
FS = 100.0


def cal_example() -> ImuCalibration:
    return ImuCalibration(gyro_bias=(0.01, -0.02, 0.003), acc_offset=(0.1, -0.2, 0.05),
                          acc_matrix=((1.01, 0.002, -0.001), (0.0, 0.99, 0.003), (0.0, 0.0, 1.002)),
                          mag_hard_iron=(12.0, -3.5, 40.0),
                          mag_soft_iron=((1.1, 0.02, 0.0), (0.02, 0.95, 0.01), (0.0, 0.01, 1.0)),
                          mounting=tuple(Rotation.from_euler("xyz", [10, -20, 30], degrees=True)
                                         .as_quat(scalar_first=True)),
                          yaw_offset_rad=0.4, device="witmotion:ABC123", note="test")


# ------------------------------------------------------------------------------------------------
# the record

def test_json_round_trip() -> None:
    c = cal_example()
    text = c.to_json()
    d = json.loads(text)
    assert d["version"] == FORMAT_VERSION and d["format"] == "perfcap.imu_calibration"
    back = ImuCalibration.from_json(text)
    assert back == c
    assert ImuCalibration.from_json(ImuCalibration().to_json()).is_identity


@pytest.mark.parametrize(("mutate", "match"), [
    (lambda d: "{not json", "not valid JSON"),
    (lambda d: [1, 2, 3], "must be a JSON object"),
    (lambda d: {k: v for k, v in d.items() if k != "version"}, "no 'version'"),
    (lambda d: {**d, "version": FORMAT_VERSION + 1}, "newer perfcap"),
    (lambda d: {**d, "version": "1"}, "positive integer"),
    (lambda d: {**d, "gyro_bias_dps": [0, 0, 0]}, "unknown field"),
    (lambda d: {**d, "format": "something.else"}, "not an IMU calibration"),
    (lambda d: {**d, "acc_offset_m_s2": [0, 0]}, "'acc_offset' must be 3 numbers"),
    (lambda d: {**d, "gyro_bias_rad_s": [0, "x", 0]}, "gyro_bias"),
    (lambda d: {**d, "mag_soft_iron": [[1, 0, 0], [0, 1, 0], [0, 0, 0]]}, "singular"),
    (lambda d: {**d, "acc_matrix": [[1, 0, 0], [0, 1, 0]]}, "3x3"),
    (lambda d: {**d, "mounting_wxyz": [1, 0, 0, 0.5]}, "unit quaternion"),
    (lambda d: {**d, "yaw_offset_rad": float("nan")}, "not finite"),
])
def test_bad_json_is_a_config_error(mutate, match: str) -> None:
    d = json.loads(cal_example().to_json())
    m = mutate(d)
    text = m if isinstance(m, str) else json.dumps(m)
    with pytest.raises(ConfigError, match=match) as e:
        ImuCalibration.from_json(text, source="cal/wrist.json")
    assert e.value.source == "cal/wrist.json"


def test_apply_vectorised_and_identity() -> None:
    c = cal_example()
    rng = np.random.default_rng(0)
    acc, gyro, mag = rng.normal(size=(50, 3)) * 9, rng.normal(size=(50, 3)), rng.normal(size=(50, 3)) * 40
    a2, g2, m2 = c.apply(acc, gyro, mag)
    acc_m, soft = np.array(c.acc_matrix), np.array(c.mag_soft_iron)
    np.testing.assert_allclose(a2, (acc - c.acc_offset) @ acc_m.T, rtol=1e-12)
    np.testing.assert_allclose(g2, gyro - c.gyro_bias, rtol=1e-12)
    np.testing.assert_allclose(m2, (mag - c.mag_hard_iron) @ soft.T, rtol=1e-12)
    a1, _, m1 = c.apply(acc[7], gyro[7], None)
    np.testing.assert_array_equal(a1, a2[7])  # one row and many rows: bit-identical
    assert m1 is None
    one_a, one_g = c.apply_one(tuple(acc[7]), tuple(gyro[7]))
    assert one_a == tuple(a2[7]) and one_g == tuple(g2[7])
    ident = ImuCalibration()
    for x, y in zip(ident.apply(acc, gyro, mag), (acc, gyro, mag), strict=True):
        np.testing.assert_array_equal(x, y)
    assert ident.is_identity and ident.sensor_identity and ident.body_identity and not c.is_identity


def test_mounting_reset_maps_gravity_to_segment_down() -> None:
    rng = np.random.default_rng(1)
    true = Rotation.from_euler("xyz", [35, -50, 10], degrees=True)  # sensor -> world, still
    acc = true.inv().apply([0, 0, G0]) + rng.normal(0, 0.02, (200, 3))
    c = ImuCalibration().with_mounting_reset(acc)
    down_body = quat_rotate(np.array(c.mounting), -acc.mean(axis=0))
    np.testing.assert_allclose(down_body / np.linalg.norm(down_body), [0, 0, -1], atol=1e-9)
    # the body orientation of that pose is level: its gravity is straight down
    q_body = c.body_orientation(true.as_quat(scalar_first=True))
    np.testing.assert_allclose(quat_rotate(q_body, [0, 0, -1.0]), [0, 0, -1], atol=0.01)
    # with a forward axis the heading of the mounting is fixed too
    m = mounting_from_gravity(acc[0], sensor_forward=(1.0, 0.0, 0.0))
    fwd = quat_rotate(np.array(m), [1.0, 0, 0])
    assert fwd[1] == pytest.approx(0.0, abs=1e-9) and fwd[0] > 0
    with pytest.raises(ConfigError):
        mounting_from_gravity([0.0, 0.0, 0.0])


def test_yaw_reset_makes_heading_zero() -> None:
    c = cal_example()
    q = Rotation.from_euler("zyx", [123, 5, -7], degrees=True).as_quat(scalar_first=True)
    c2 = c.with_yaw_reset(q)
    assert quat_heading(c2.body_orientation(q)) == pytest.approx(0.0, abs=1e-9)
    # turning the sensor 30 deg about vertical afterwards reads 30 deg
    q30 = (Rotation.from_euler("z", 30, degrees=True) * Rotation.from_quat(q, scalar_first=True)
           ).as_quat(scalar_first=True)
    assert math.degrees(quat_heading(c2.body_orientation(q30))) == pytest.approx(30.0, abs=1e-6)


# ------------------------------------------------------------------------------------------------
# stillness and the explicit still period

def test_still_bias_with_standard_error() -> None:
    rng = np.random.default_rng(2)
    bias = np.array([0.5, -0.25, 0.1]) * D2R
    n = 2000
    g = bias + rng.normal(0, 0.2 * D2R, (n, 3))
    a = np.array([0, 0, G0]) + rng.normal(0, 0.02, (n, 3))
    sb = still_bias(g, a, np.arange(n) / FS)
    assert np.all(np.abs(sb.bias - bias) < 4 * sb.stderr)
    np.testing.assert_allclose(sb.stderr, 0.2 * D2R / math.sqrt(n), rtol=0.35)
    assert sb.duration_s == pytest.approx((n - 1) / FS) and sb.n == n
    with pytest.raises(ConfigError, match="moved"):
        still_bias(g + np.sin(np.arange(n) / 20)[:, None] * 5 * D2R, a)
    with pytest.raises(ConfigError, match="turning"):
        still_bias(g + np.array([0, 0, 20 * D2R]), a)
    with pytest.raises(ConfigError, match="at least"):
        still_bias(g[:5], a[:5])


def test_still_mask_and_segments() -> None:
    rng = np.random.default_rng(3)
    n = 1000
    g = rng.normal(0, 0.1 * D2R, (n, 3))
    a = np.array([0, 0, G0]) + rng.normal(0, 0.02, (n, 3))
    g[400:600] += rng.normal(0, 30 * D2R, (200, 3))
    a[400:600] += rng.normal(0, 2.0, (200, 3))
    segs = still_segments(still_mask(a, g, FS), min_len=100)
    assert len(segs) == 2
    assert segs[0][0] == 0 and 370 <= segs[0][1] <= 400 and 600 <= segs[1][0] <= 630 and segs[1][1] == n


# ------------------------------------------------------------------------------------------------
# automatic bias

def _scenario(segments, bias, mag_world=None, seed=0):
    """Concatenated segments (seconds, world rate rad/s, start orientation or None), each broken from the
    next by 0.1 s of shaking; returns t, gyro, acc, mag."""
    rng = np.random.default_rng(seed)
    ts, gs, as_, ms = [], [], [], []
    r = Rotation.identity()
    t0 = 0.0
    for dur, w, start in segments:
        r = start if start is not None else r
        n = int(dur * FS)
        t = np.arange(n) / FS
        rr = Rotation.from_rotvec(np.outer(t, w)) * r
        g = rr.inv().apply(np.tile(w, (n, 1))) + bias + rng.normal(0, 0.1 * D2R, (n, 3))
        a = rr.inv().apply([0, 0, G0]) + rng.normal(0, 0.02, (n, 3))
        g[-10:] += rng.normal(0, 30 * D2R, (10, 3))  # a bump between segments
        ts.append(t0 + t)
        gs.append(g)
        as_.append(a)
        if mag_world is not None:
            ms.append(rr.inv().apply(mag_world) + rng.normal(0, 0.2, (n, 3)))
        r = rr[-1]
        t0 += dur
    return (np.concatenate(ts), np.vstack(gs), np.vstack(as_), np.vstack(ms) if ms else None)


BIAS = np.array([0.3, -0.2, 0.25]) * D2R
TURN = [0, 0, 2 * D2R]  # 2 deg/s about gravity: looks exactly like bias to a naive detector


def test_auto_bias_on_a_real_walk_finds_the_standing_still_period() -> None:
    f = (Path(__file__).resolve().parents[4] / "shared" / "traces" / "a_imu_csv" / "gaitmap_walk"
         / "imu_sample_not_rotated.csv")
    if not f.is_file():
        pytest.skip(f"gait trace not found at {f}")
    d = np.loadtxt(f, delimiter=",", skiprows=2, max_rows=2048)  # 10 s: stand, then walk
    t, g, a = np.arange(len(d)) / 204.8, np.radians(d[:, 10:13]), d[:, 7:10]  # right foot
    est = GyroBiasEstimator()
    est.update(t, g, a)
    e = est.finish()
    (t0, t1), = est.still_periods()  # the foot is never still while walking, only while standing
    assert t0 < 0.05 and 0.6 < t1 < 0.8
    sb = still_bias(g[: int(0.6 * 204.8)], a[: int(0.6 * 204.8)])
    np.testing.assert_allclose(e.bias, sb.bias, atol=4 * float(sb.stderr.max()) + 0.02 * D2R)
    assert e.confidence < 0.5  # 0.7 s in one orientation, no magnetometer: not enough to be sure


def test_auto_bias_not_fooled_by_slow_rotation_about_gravity() -> None:
    t, g, a, _ = _scenario([(30, TURN, None)], BIAS)
    naive = g.mean(axis=0)
    assert abs(naive[2] - BIAS[2] - 2 * D2R) < 0.05 * D2R  # the naive mean takes the turn for bias
    e = estimate_gyro_bias(t, g, a)
    # without a magnetometer and with one orientation it cannot tell: it says so
    assert e.confidence < 0.5
    assert e.std[2] > 0.2 * D2R
    # the components across gravity are pinned down, as they are observable from the accelerometer
    np.testing.assert_allclose(e.bias[:2], BIAS[:2], atol=0.02 * D2R)
    # imufusion's own offset learner (|w| < 3 deg/s for 3 s = still) learns the turn as bias
    import imufusion

    b = imufusion.Bias()
    s = imufusion.BiasSettings()
    s.sample_rate = FS
    b.set_settings(s)
    for row in np.degrees(g):
        b.update(row)
    assert abs(float(b.get_offset()[2]) - math.degrees(BIAS[2]) - 2.0) < 0.2


def test_auto_bias_uses_the_magnetometer_heading() -> None:
    t, g, a, m = _scenario([(30, TURN, None)], BIAS, mag_world=np.array([0, 20, -40.0]))
    e = estimate_gyro_bias(t, g, a, m)
    np.testing.assert_allclose(e.bias, BIAS, atol=0.03 * D2R)
    assert e.confidence > 0.9


def test_auto_bias_rejects_a_turning_period_that_disagrees_with_other_orientations() -> None:
    side = Rotation.from_euler("x", 90, degrees=True)
    t, g, a, _ = _scenario([(10, [0, 0, 0], side), (10, [0, 0, 0], Rotation.from_euler("y", 90, degrees=True)),
                            (30, TURN, Rotation.identity())], BIAS)
    e = estimate_gyro_bias(t, g, a)
    assert e.rejected == 1 and e.periods == 2
    np.testing.assert_allclose(e.bias, BIAS, atol=0.03 * D2R)
    assert e.confidence > 0.9


def test_auto_bias_removes_slow_tilting() -> None:
    # 1 deg/s about a horizontal axis: the gravity direction drifts, so this part is observable
    t, g, a, _ = _scenario([(20, [1 * D2R, 0, 0], None)], BIAS)
    e = estimate_gyro_bias(t, g, a)
    assert abs(g.mean(axis=0)[0] - BIAS[0]) > 0.9 * D2R  # naive
    assert abs(e.bias[0] - BIAS[0]) < 0.05 * D2R


def test_auto_bias_streaming_equals_batch_and_is_confident_with_orientations() -> None:
    segs = [(8, [0, 0, 0], Rotation.identity()), (8, [0, 0, 0], Rotation.from_euler("x", 90, degrees=True)),
            (8, [0, 0, 0], Rotation.from_euler("y", -90, degrees=True))]
    t, g, a, _ = _scenario(segs, BIAS, seed=5)
    batch = estimate_gyro_bias(t, g, a)
    est = GyroBiasEstimator()
    assert est.estimate.confidence == 0.0 and est.estimate.periods == 0
    for i in range(0, len(t), 13):
        est.update(t[i:i + 13], g[i:i + 13], a[i:i + 13])
    stream = est.finish()
    np.testing.assert_allclose(stream.bias, batch.bias, atol=1e-12)
    assert stream.periods == 3 and stream.confidence > 0.9
    np.testing.assert_allclose(stream.bias, BIAS, atol=0.02 * D2R)
    assert len(est.still_periods()) == 3


# ------------------------------------------------------------------------------------------------
# accelerometer fit

def _poses(n_dirs: int, seed: int = 0):
    rng = np.random.default_rng(seed)
    d = rng.normal(size=(n_dirs, 3))
    d[:6] = [[1, 0, 0], [-1, 0, 0], [0, 1, 0], [0, -1, 0], [0, 0, 1], [0, 0, -1]]
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    acc_m = np.array([[1.02, 0.01, -0.015], [0.0, 0.98, 0.012], [0.0, 0.0, 1.01]])
    o = np.array([0.2, -0.15, 0.3])
    raw = (d * G0) @ np.linalg.inv(acc_m).T + o + rng.normal(0, 0.003, (n_dirs, 3))
    return raw, acc_m, o


def test_accelerometer_fit_full_and_diagonal() -> None:
    raw, acc_m, o = _poses(16)
    f = fit_accelerometer(raw)
    assert f.model == "full" and 12 <= f.distinct <= 16
    np.testing.assert_allclose(f.offset, o, atol=0.01)
    np.testing.assert_allclose(f.matrix, acc_m, atol=0.002)
    assert f.residual_rms < 0.01 < f.raw_rms
    f6 = fit_accelerometer(raw[:6])  # the six faces: offset and scale
    assert f6.model == "diagonal"
    np.testing.assert_allclose(f6.offset, o, atol=0.03)
    np.testing.assert_allclose(np.diag(f6.matrix), np.diag(acc_m), atol=0.01)


def test_accelerometer_fit_rejects_too_few_or_too_similar() -> None:
    raw, _, _ = _poses(16)
    with pytest.raises(ConfigError, match="at least 6 distinct"):
        fit_accelerometer(raw[:4])
    with pytest.raises(ConfigError, match="at least 9 distinct"):
        fit_accelerometer(raw[:8], model="full")
    tilt = Rotation.from_rotvec(np.random.default_rng(1).normal(0, 0.3, (12, 3)))
    similar = tilt.apply([0, 0, G0])  # all roughly z-up
    with pytest.raises(ConfigError, match=r"too similar|distinct"):
        fit_accelerometer(similar)
    one_sided = raw.copy()
    one_sided[:, 0] = np.abs(one_sided[:, 0])  # the x axis never points down
    with pytest.raises(ConfigError, match="too similar: no pose with the -x axis"):
        fit_accelerometer(one_sided)


def test_still_poses_from_a_recording() -> None:
    rng = np.random.default_rng(4)
    chunks_a, chunks_g = [], []
    for d in ([0, 0, 1], [1, 0, 0], [0, -1, 0]):
        chunks_a.append(np.array(d) * G0 + rng.normal(0, 0.02, (300, 3)))
        chunks_g.append(rng.normal(0, 0.1 * D2R, (300, 3)))
        chunks_a.append(rng.normal(0, 3, (100, 3)))
        chunks_g.append(rng.normal(0, 50 * D2R, (100, 3)))
    a, g = np.vstack(chunks_a), np.vstack(chunks_g)
    poses = still_poses(np.arange(len(a)) / FS, a, g, min_still_s=1.5)
    np.testing.assert_allclose(poses, [[0, 0, G0], [G0, 0, 0], [0, -G0, 0]], atol=0.05)


# ------------------------------------------------------------------------------------------------
# magnetometer fit

def test_magnetometer_ellipsoid_fit_known_answer() -> None:
    rng = np.random.default_rng(5)
    d = rng.normal(size=(3000, 3))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    soft = np.array([[1.1, 0.05, 0.02], [0.05, 0.9, -0.03], [0.02, -0.03, 1.0]])
    h = np.array([12.0, -30.0, 5.0])
    raw = (d * 45.0) @ np.linalg.inv(soft).T + h + rng.normal(0, 0.3, (3000, 3))
    raw[:60] += 25.0  # a disturbance: trimmed as outliers
    f = fit_magnetometer(raw)
    assert f.model == "ellipsoid" and f.coverage > 0.95
    np.testing.assert_allclose(f.hard_iron, h, atol=0.2)
    # calibrated readings lie on a sphere of radius `field`: soft iron = `soft` scaled to that radius
    assert f.field == pytest.approx(45.0 / np.cbrt(np.linalg.det(soft)), rel=0.005)
    np.testing.assert_allclose(f.soft_iron * 45.0 / f.field, soft, atol=0.005)
    assert f.spread_after < 0.01
    assert f.spread_before > 0.1
    assert f.inliers <= 3000 - 55


def test_magnetometer_fit_rejects_poor_coverage_and_planar_dances() -> None:
    rng = np.random.default_rng(6)
    ang = rng.uniform(0, 2 * np.pi, 800)
    ring = np.stack([np.cos(ang), np.sin(ang), np.full(800, 0.2)], axis=1) * 40 + rng.normal(0, 0.3, (800, 3))
    with pytest.raises(ConfigError, match="one plane"):
        fit_magnetometer(ring)
    cap = Rotation.from_rotvec(rng.normal(0, 0.15, (800, 3))).apply([0, 0, 40.0])  # barely moved
    with pytest.raises(ConfigError, match="poor coverage"):
        fit_magnetometer(cap)
    with pytest.raises(ConfigError, match="at least 50"):
        fit_magnetometer(ring[:10])


def test_magnetometer_fit_on_real_data(xio_csv: Path) -> None:
    m = np.loadtxt(xio_csv, delimiter=",", skiprows=1, usecols=(7, 8, 9), max_rows=10000)
    f = fit_magnetometer(m)
    # a hand-held dance turned mostly about one axis: coverage too low for soft iron, hard iron only
    assert f.model == "sphere" and 0.25 <= f.coverage < 0.5
    assert 40.0 < f.field < 50.0  # Earth's field, in uT
    assert f.spread_after < f.spread_before
    assert np.linalg.norm(f.hard_iron) < 5.0  # x-io ships this data already calibrated
