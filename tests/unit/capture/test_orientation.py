"""Orientation filters and the orientation processor: conventions, dt from timestamps, gaps, mixed-rate
magnetometer, the measured library pitfalls, real data, and Sample vs SampleBatch equivalence."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from capture.calibration import G0, ImuCalibration, quat_heading
from capture.errors import ConfigError
from capture.orientation import (
    FILTERS,
    FLAG_GAP,
    FLAG_INIT,
    FLAG_NO_MAG,
    FLAG_SKIPPED,
    OrientationFilter,
    OrientationProcessor,
    check_imu_stream,
    check_mag_stream,
    gravity_from_quaternion,
)
from capture.quat import quat_conj, quat_mul
from capture.sample import NO_TIME, DeviceIdentity, Sample, SampleBatch, StreamInfo

D2R = math.pi / 180
GAIT_CSV = (Path(__file__).resolve().parents[4] / "shared" / "traces" / "a_imu_csv" / "gaitmap_walk"
            / "imu_sample_not_rotated.csv")
IMU_CH = ("ax", "ay", "az", "gx", "gy", "gz", "temp")
SI = ("m/s^2",) * 3 + ("rad/s",) * 3 + ("degC",)


def imu_info(name: str = "wrist/imu", units: tuple[str, ...] = SI, rate: float | None = 100.0, kind: str = "imu",
             frame: str | None = "sensor frame", channels: tuple[str, ...] = IMU_CH) -> StreamInfo:
    return StreamInfo(name, kind, channels, units, rate, DeviceIdentity(kind="test", name=name.split("/", 1)[0]), frame)


def mag_info(name: str = "wrist/mag", units: tuple[str, ...] = ("uT",) * 3, frame: str | None = "sensor frame",
             rate: float = 20.0) -> StreamInfo:
    return StreamInfo(name, "mag", ("mx", "my", "mz"), units, rate,
                      DeviceIdentity(kind="test", name=name.split("/", 1)[0]), frame)


def angle_deg(q1: np.ndarray, q2: np.ndarray) -> np.ndarray:
    d = quat_mul(quat_conj(q1), q2)
    return np.degrees(2 * np.arctan2(np.linalg.norm(d[..., 1:], axis=-1), np.abs(d[..., 0])))


def motion(rate_hz: float, seconds: float, omega_world, *, q0: Rotation | None = None, mag_world=None,
           noise: float = 0.0, seed: int = 0):
    """A sensor turning at a constant world-frame rate: (t, gyro rad/s, acc m/s^2, mag, true sensor->world)."""
    rng = np.random.default_rng(seed)
    n = round(rate_hz * seconds) + 1
    t = np.arange(n) / rate_hz
    w = np.asarray(omega_world, float)
    r = Rotation.from_rotvec(np.outer(t, w)) * (q0 or Rotation.identity())
    gyro = r.inv().apply(np.tile(w, (n, 1)))
    acc = r.inv().apply([0.0, 0.0, G0])
    mag = None if mag_world is None else r.inv().apply(mag_world)
    if noise:
        gyro = gyro + rng.normal(0, noise * D2R, gyro.shape)
        acc = acc + rng.normal(0, noise * 0.2, acc.shape)
    return t, gyro, acc, mag, r.as_quat(scalar_first=True)


# ------------------------------------------------------------------------------------------------
# stream boundary

def test_imu_stream_units_converted() -> None:
    ch = check_imu_stream(imu_info(units=("g", "g", "g", "deg/s", "deg/s", "deg/s", "degC")))
    assert ch.acc_scale == pytest.approx(G0) and ch.gyro_scale == pytest.approx(math.pi / 180)
    ch = check_imu_stream(imu_info())
    assert (ch.acc_idx, ch.gyro_idx, ch.acc_scale, ch.gyro_scale) == ((0, 1, 2), (3, 4, 5), 1.0, 1.0)


@pytest.mark.parametrize(("info", "words"), [
    (imu_info(units=("m/s", "m/s^2", "m/s^2", "rad/s", "rad/s", "rad/s", "degC")), ["wrist/imu", "ax", "'m/s'"]),
    (imu_info(units=(*SI[:3], "rpm", "rad/s", "rad/s", "degC")), ["wrist/imu", "gx", "'rpm'"]),
    (imu_info(units=(*SI[:3], "rad/s", "deg/s", "rad/s", "degC")), ["wrist/imu", "different units"]),
    (imu_info(channels=("ax", "ay", "az", "gx", "gy", "wz", "temp")), ["wrist/imu", "'gz' not found"]),
    (imu_info(kind="euler"), ["wrist/imu", "'euler'"]),
    (imu_info(frame="left-handed x fwd"), ["wrist/imu", "left-handed"]),
])
def test_imu_stream_errors_name_stream_channel_unit(info: StreamInfo, words: list[str]) -> None:
    with pytest.raises(ConfigError) as e:
        check_imu_stream(info)
    for w in words:
        assert w in str(e.value)
    assert e.value.source == info.name


def test_mag_stream_checks() -> None:
    assert check_mag_stream(mag_info(), imu_info()).idx == (0, 1, 2)
    with pytest.raises(ConfigError, match=r"wrist/mag.*'uT', 'uT', 'nT'"):
        check_mag_stream(mag_info(units=("uT", "uT", "nT")))
    with pytest.raises(ConfigError, match=r"wrist/mag: channel mx has unit 'm/s\^2'"):
        check_mag_stream(mag_info(units=("m/s^2",) * 3))
    with pytest.raises(ConfigError, match="differs from wrist/imu"):
        check_mag_stream(mag_info(frame="AK8963 axes"), imu_info(frame="MPU6500 axes"))
    with pytest.raises(ConfigError, match="no IMU stream of the same device"):
        OrientationProcessor([imu_info(), mag_info("ankle/mag")])


def test_settings_validated() -> None:
    with pytest.raises(ConfigError, match="unknown orientation filter"):
        OrientationFilter("kalman")
    with pytest.raises(ConfigError, match="unknown orientation setting"):
        OrientationFilter("fusion", gian=0.5)
    with pytest.raises(ConfigError, match="max_gap_s"):
        OrientationFilter("fusion", max_gap_s=0)


# ------------------------------------------------------------------------------------------------
# one convention for every filter

def test_imufusion_convention_keyword_is_ignored_but_ours_is_enu() -> None:
    import imufusion

    # the measured pitfall (imufusion 1.3.3): the constructor keyword is silently dropped (a later
    # imufusion may honour it; either way the keyword leaves one of these two) ...
    s = imufusion.AhrsSettings(convention=imufusion.CONVENTION_ENU)
    assert s.convention in (imufusion.CONVENTION_NWU, imufusion.CONVENTION_ENU)
    # ... so the wrapper assigns every setting and reads it back: ENU whatever the version does
    f = OrientationFilter("fusion", nominal_rate_hz=100)
    t, g, a, m, _ = motion(100, 4, [0, 0, 0], mag_world=[0, 20, -40])
    q = f.update_many(t, g, a, m).q
    assert angle_deg(q[-1], np.array([1.0, 0, 0, 0])) < 0.5  # sensor y points north: identity in ENU


@pytest.mark.parametrize("kind", FILTERS)
def test_every_filter_reports_enu_sensor_to_world(kind: str) -> None:
    # a still sensor tilted 30 deg about x, heading 40 deg; field north with a 60 deg dip
    truth = Rotation.from_euler("z", 40, degrees=True) * Rotation.from_euler("x", 30, degrees=True)
    mag_world = np.array([0.0, math.cos(math.radians(60)), -math.sin(math.radians(60))]) * 45
    t, g, a, m, q_true = motion(100, 8, [0, 0, 0], q0=truth, mag_world=mag_world, noise=0.05, seed=1)
    r = OrientationFilter(kind).update_many(t, g, a, m)
    err = angle_deg(r.q[-100:], q_true[-100:])
    assert float(np.median(err)) < 1.0, f"{kind}: {np.median(err):.2f} deg from the true ENU orientation"
    assert math.degrees(quat_heading(r.q[-1])) == pytest.approx(40, abs=1.0)
    # gravity output: what the accelerometer reads from gravity, in the sensor frame
    np.testing.assert_allclose(r.gravity[-1], a[-1], atol=0.1)
    np.testing.assert_allclose(np.linalg.norm(r.linear_acc[-100:], axis=1), 0, atol=0.15)


def test_gravity_from_quaternion_is_sensor_frame_up() -> None:
    q = Rotation.from_euler("y", 90, degrees=True).as_quat(scalar_first=True)  # sensor x points down
    np.testing.assert_allclose(gravity_from_quaternion(q), [-G0, 0, 0], atol=1e-12)


# ------------------------------------------------------------------------------------------------
# dt from timestamps

@pytest.mark.parametrize("kind", FILTERS)
def test_same_motion_at_100_and_256_hz_gives_same_orientation(kind: str) -> None:
    w = np.array([0.6, -0.4, 0.9])  # rad/s, tilting and turning: gyro and accelerometer both change
    finals = []
    for rate in (100.0, 256.0):
        t, g, a, _, q_true = motion(rate, 2.0, w, q0=Rotation.from_euler("x", 10, degrees=True))
        q = OrientationFilter(kind).update_many(t, g, a).q
        assert angle_deg(q[-1], q_true[-1]) < 1.5, f"{kind} at {rate} Hz"
        finals.append(q[-1])
    assert angle_deg(finals[0], finals[1]) < 1.0


def test_library_default_rate_pitfall_shown() -> None:
    from ahrs.filters import Madgwick

    # 256 Hz data through ahrs with its default Dt (100 Hz): the 90 deg turn comes out 2.56x too large
    t, g, a, _, _ = motion(256.0, 1.0, [0, 0, math.pi / 2])
    f = Madgwick()
    q = np.array([1.0, 0, 0, 0])
    for i in range(1, len(t)):
        q = f.updateIMU(q, g[i], a[i])
    naive = math.degrees(quat_heading(q))
    ours = math.degrees(quat_heading(OrientationFilter("madgwick").update_many(t, g, a).q[-1]))
    assert naive == pytest.approx(math.remainder(90 * 2.56, 360), abs=1.0)  # 230 deg, i.e. -130
    assert ours == pytest.approx(90, abs=0.5)


def test_dropped_samples_on_real_data_change_little(xio_csv: Path) -> None:
    d = np.loadtxt(xio_csv, delimiter=",", skiprows=1, max_rows=4000)
    t, g, a = d[:, 0], np.radians(d[:, 1:4]), d[:, 4:7] * G0
    full = OrientationFilter("fusion").update_many(t, g, a).q
    keep = np.random.default_rng(2).random(len(t)) > 0.3
    keep[0] = True
    part = OrientationFilter("fusion").update_many(t[keep], g[keep], a[keep]).q
    err = angle_deg(full[keep], part)
    assert float(np.median(err[500:])) < 1.0
    # the same data with a fixed 100 Hz dt (what a default rate does) is much worse
    fixed = OrientationFilter("fusion").update_many(np.arange(keep.sum()) / 100.0, g[keep], a[keep]).q
    assert float(np.median(angle_deg(full[keep], fixed)[500:])) > 3 * float(np.median(err[500:]))


@pytest.fixture
def gait() -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Left-foot IMU of the gaitmap walk (204.8 Hz, acc m/s^2, gyro rad/s), first 12 s."""
    if not GAIT_CSV.is_file():
        pytest.skip(f"gait trace not found at {GAIT_CSV}")
    d = np.loadtxt(GAIT_CSV, delimiter=",", skiprows=2, max_rows=int(12 * 204.8))
    return np.arange(len(d)) / 204.8, np.radians(d[:, 4:7]), d[:, 1:4]


@pytest.mark.parametrize("kind", ["fusion", "mahony"])
def test_real_walk_at_half_rate_stays_close_but_a_default_rate_does_not(gait, kind: str) -> None:
    t, g, a = gait
    full = OrientationFilter(kind).update_many(t, g, a).q
    half = OrientationFilter(kind).update_many(t[::2], g[::2], a[::2]).q  # 102.4 Hz, same motion
    err = angle_deg(full[::2], half)
    # half the samples of a 700 deg/s foot swing lose some motion (measured: ~3.5 deg median)
    assert float(np.median(err)) < 5.0, f"{kind}: median {np.median(err):.2f} deg"
    # a filter told the 204.8 Hz data comes at a fixed 100 Hz (a default rate) is lost (~88 deg)
    wrong = OrientationFilter(kind).update_many(np.arange(len(t)) / 100.0, g, a).q
    assert float(np.median(angle_deg(full, wrong))) > 10 * float(np.median(err))


# ------------------------------------------------------------------------------------------------
# gaps, bad times, invalid input

@pytest.mark.parametrize("kind", ["fusion", "madgwick"])
def test_gap_is_not_integrated_across(kind: str) -> None:
    t, g, a, _, _ = motion(100, 3.0, [0, 0, 1.0])  # turning 1 rad/s about vertical
    cut = (t > 1.0) & (t < 3.0)  # a 2 s hole (unplugged): the sensor turned 2 rad meanwhile
    tk, gk, ak = t[~cut], g[~cut], a[~cut]
    f = OrientationFilter(kind)
    r = f.update_many(tk, gk, ak)
    i = int(np.flatnonzero(tk >= 3.0)[0])
    assert r.flags[i] & FLAG_GAP and r.flags[i] & FLAG_INIT
    assert f.gaps == 1 and f.stats()["gaps"] == 1
    h_before, h_after = math.degrees(quat_heading(r.q[i - 1])), math.degrees(quat_heading(r.q[i]))
    assert h_after == pytest.approx(h_before, abs=0.5)  # kept heading, no 2 s x rate jump
    assert angle_deg(r.q[i], r.q[i - 1]) < 1.0


def test_gap_threshold_follows_the_nominal_rate() -> None:
    # at 200 Hz a 0.2 s hole (a reconnect) is a gap (> 10 periods); 3 dropped samples are integrated
    t, g, a, _, q_true = motion(200, 3.0, [0.8, 0.0, 0.5], noise=0.05)
    keep = ~((t > 1.0) & (t < 1.2)) & ~((t > 2.0) & (t < 2.016))
    f = OrientationFilter("fusion", nominal_rate_hz=200)
    r = f.update_many(t[keep], g[keep], a[keep])
    assert f.gaps == 1 and int(np.count_nonzero(r.flags & FLAG_GAP)) == 1
    # re-initialised from the accelerometer (tilt; the heading turned in the hole is lost: no magnetometer)
    g_true = gravity_from_quaternion(q_true[keep])
    tilt = np.degrees(np.arccos(np.clip(np.sum(r.gravity * g_true, axis=1) / G0 ** 2, -1, 1)))
    assert float(np.max(tilt[t[keep] > 1.5])) < 1.0
    assert OrientationFilter("fusion").settings["max_gap_s"] == 0.5  # without a nominal rate: max_gap_s only


def test_non_increasing_and_invalid_samples_are_skipped_and_counted() -> None:
    t, g, a, _, _ = motion(100, 1.0, [0.3, 0, 0])
    t = t.copy()
    g = g.copy()
    t[50] = t[49]          # duplicate time
    t[60] = t[58]          # backwards
    g[70] = np.nan         # invalid gyro
    f = OrientationFilter("fusion")
    r = f.update_many(t, g, a)
    for i in (50, 60, 70):
        assert r.flags[i] & FLAG_SKIPPED
        np.testing.assert_array_equal(r.q[i], r.q[i - 1])
    assert (f.non_increasing, f.rejected, f.gaps) == (2, 1, 0)
    assert f.integrated == len(t) - 1 - 3  # the first sample initialises
    # streaming continues from the last accepted time
    r2 = f.update(t[-1], g[-1], a[-1])
    assert r2.flags[0] & FLAG_SKIPPED


def test_streaming_equals_batch() -> None:
    t, g, a, m, _ = motion(100, 3.0, [0.5, -0.2, 0.8], mag_world=[0, 20, -40], noise=0.1)
    whole = OrientationFilter("fusion").update_many(t, g, a, m)
    f = OrientationFilter("fusion")
    parts = [f.update_many(t[i:i + 37], g[i:i + 37], a[i:i + 37], m[i:i + 37]) for i in range(0, len(t), 37)]
    np.testing.assert_array_equal(np.vstack([p.q for p in parts]), whole.q)


@pytest.mark.parametrize("settings", [{}, {"gyro_offset": True}])
def test_one_sample_path_equals_batch_bit_for_bit(settings: dict[str, bool]) -> None:
    t, g, a, _, _ = motion(100, 3.0, [0.5, -0.2, 0.8], noise=0.1)
    t[150:] += 1.0  # a gap: re-initialised
    t[200] = t[199]  # not after the previous sample: skipped
    g[220] = np.nan  # an invalid gyro: skipped
    a[240] = np.nan  # no valid accelerometer: a gyro-only update
    whole = OrientationFilter("fusion", **settings).update_many(t, g, a)
    f = OrientationFilter("fusion", **settings)
    ones = [f.update_one(float(t[i]), tuple(g[i].tolist()), tuple(a[i].tolist())) for i in range(len(t))]
    np.testing.assert_array_equal(np.array([q for q, _ in ones]), whole.q)
    assert [flags for _, flags in ones] == whole.flags.tolist()


# ------------------------------------------------------------------------------------------------
# mixed rates

def test_mag_at_lower_rate_is_held_and_not_used_when_stale() -> None:
    mag_world = np.array([0.0, 25.0, -40.0])
    t, g, a, m, q_true = motion(200, 6.0, [0, 0, 0.3], q0=Rotation.from_euler("z", 50, degrees=True),
                                mag_world=mag_world, noise=0.05)
    f = OrientationFilter("fusion", nominal_rate_hz=200)
    slow = np.arange(0, len(t), 10)  # 20 Hz magnetometer
    slow = slow[t[slow] <= 4.0]      # ... which stops at 4 s
    f.add_mag(t[slow], m[slow])
    r = f.update_many(t, g, a)
    fresh = t <= 4.0 + 0.25
    assert not np.any(r.flags[fresh] & FLAG_NO_MAG)
    assert np.all(r.flags[t > 4.0 + 0.25 + 1e-9] & FLAG_NO_MAG)
    assert f.mag_used == int(fresh.sum()) and f.mag_stale == int((~fresh).sum())
    err = angle_deg(r.q, q_true)
    assert float(np.median(err[(t > 3.0) & (t < 4.0)])) < 1.0  # heading from the 20 Hz magnetometer
    # the same through the processor, with the magnetometer as its own Sample stream
    p = OrientationProcessor([imu_info(rate=200.0), mag_info()], "fusion")
    out: list = []
    p.bind(out.append)
    vals = np.hstack([a, g, np.full((len(t), 1), 25.0)])
    tb = (t * 1e9).astype(np.int64) + 10**9
    mi = 0
    for i in range(len(t)):
        while mi < len(slow) and slow[mi] <= i:
            k = slow[mi]
            p.on_item(Sample("wrist/mag", mi, int(tb[k]), None, int(tb[k]), tuple(m[k])))
            mi += 1
        p.on_item(Sample("wrist/imu", i, int(tb[i]), None, int(tb[i]), tuple(vals[i])))
    q_p = np.array([s.values for s in out if s.stream == "wrist/orientation"])
    assert float(np.median(angle_deg(q_p, q_true)[(t > 3.0) & (t < 4.0)])) < 1.0
    assert p.mag_in == len(slow)


# ------------------------------------------------------------------------------------------------
# measured library pitfalls

def _spin(rate_hz: float = 100.0):
    """Still 2 s, a 1000 deg/s tumble for 3 s on a 5 cm arm (centripetal acceleration), still 20 s."""
    rng = np.random.default_rng(1)
    dt = 1 / rate_hz
    n = int(25 * rate_hz)
    i1, i2 = int(2 * rate_hz), int(5 * rate_hz)
    axis = np.array([1, 0.3, 0.2]) / np.linalg.norm([1, 0.3, 0.2])
    w = np.zeros((n, 3))
    w[i1:i2] = axis * math.radians(1000)
    r = Rotation.from_rotvec(np.cumsum(np.vstack([np.zeros(3), w[:-1]]) * dt, axis=0))  # about a fixed axis
    acc = r.inv().apply([0, 0, G0])
    acc[i1:i2] += -np.cross(w[i1:i2], np.cross(w[i1:i2], [0.05, 0, 0]))
    return (np.arange(n) * dt, w + rng.normal(0, math.radians(0.1), w.shape), acc + rng.normal(0, 0.02, acc.shape),
            i2, n)


def test_mahony_winds_up_after_a_fast_spin_at_default_gains_and_ours_does_not() -> None:
    from ahrs.filters import Mahony

    t, w, acc, i2, n = _spin()
    f = Mahony()  # library defaults: k_P=1, k_I=0.3
    q = np.array([1.0, 0, 0, 0])
    head = []
    for i in range(n):
        q = f.updateIMU(q, w[i], acc[i], dt=0.01)
        head.append(quat_heading(np.asarray(q)))
    h = np.degrees(np.unwrap(head))
    k1, k2 = i2 + 500, n - 1
    raw_drift = (h[k2] - h[k1]) / ((k2 - k1) * 0.01)
    assert np.linalg.norm(f.b) > math.radians(2)  # wound-up bias kept after the spin ...
    assert abs(raw_drift) > 2.0                    # ... a steady heading drift of deg/s while still
    ours = OrientationFilter("mahony")
    r = ours.update_many(t, w, acc)
    h = np.degrees(np.unwrap(quat_heading(r.q)))
    assert abs((h[k2] - h[k1]) / ((k2 - k1) * 0.01)) < 0.1
    assert np.linalg.norm(ours.mahony_bias) <= math.radians(3) + 1e-12
    # and it still estimates tilt after the spin
    up = gravity_from_quaternion(r.q[-1]) / G0
    tilt = np.degrees(np.arccos(np.clip(up @ (acc[-1] / np.linalg.norm(acc[-1])), -1, 1)))
    assert tilt < 1.0


def test_zero_gyro_reading_still_corrects_tilt() -> None:
    from ahrs.filters import Madgwick

    # a quantised gyro at rest reads exactly 0: ahrs skips the whole update, accelerometer included
    acc = Rotation.from_euler("x", 20, degrees=True).inv().apply([0, 0, G0])
    q = Madgwick().updateIMU(np.array([1.0, 0, 0, 0]), np.zeros(3), acc, dt=0.01)
    np.testing.assert_array_equal(np.asarray(q), [1.0, 0, 0, 0])
    f = OrientationFilter("madgwick")
    n = 3000
    f.update_many(np.arange(1) / 100, np.zeros((1, 3)), [[0, 0, G0]])  # start level
    r = f.update_many(np.arange(1, n) / 100, np.zeros((n - 1, 3)), np.tile(acc, (n - 1, 1)))
    np.testing.assert_allclose(r.gravity[-1], acc, atol=0.05)


def test_ekf_magnetic_reference_is_set_from_the_data() -> None:
    from ahrs.filters import EKF

    # a field with a 20 deg dip (far from the library's Munich default, ~64 deg)
    truth = Rotation.from_euler("z", -70, degrees=True)
    mag_world = np.array([0.0, math.cos(math.radians(20)), -math.sin(math.radians(20))]) * 30
    t, g, a, m, q_true = motion(100, 5, [0, 0, 0], q0=truth, mag_world=mag_world, noise=0.05)
    ours = OrientationFilter("ekf").update_many(t, g, a, m).q
    assert float(np.median(angle_deg(ours[-100:], q_true[-100:]))) < 1.0
    lib = EKF(frame="NED")  # what a caller gets without magnetic_ref ...
    with pytest.raises(ValueError):  # ... and, built without mag data, it cannot take a magnetometer at all
        lib.update(ours[0].copy(), g[1], a[1], m[1], dt=0.01)
    lib.mag = m  # (the wrapper sets this attribute per sample to choose the measurement model)
    q = ours[0].copy()
    for i in range(1, len(t)):
        q = lib.update(q, g[i], a[i], m[i], dt=0.01)
    assert angle_deg(q, q_true[-1]) > 5.0


def test_xio_every_filter_agrees_with_fusion(xio_csv: Path) -> None:
    d = np.loadtxt(xio_csv, delimiter=",", skiprows=1, max_rows=2500)
    t, g, a, m = d[:, 0], np.radians(d[:, 1:4]), d[:, 4:7] * G0, d[:, 7:10]
    ref = OrientationFilter("fusion").update_many(t, g, a, m).q
    for kind in FILTERS[1:]:
        q = OrientationFilter(kind).update_many(t, g, a, m).q
        med = float(np.median(angle_deg(ref, q)[500:]))
        assert med < 3.0, f"{kind} differs from fusion by {med:.2f} deg (median)"


# ------------------------------------------------------------------------------------------------
# the processor

def _batches(t, a, g, name="wrist/imu", size=25):
    vals = np.hstack([a, g, np.full((len(t), 1), 25.0)])
    tb = (np.asarray(t) * 1e9).astype(np.int64) + 5 * 10**9
    out = []
    for k in range(0, len(t), size):
        sl = slice(k, k + size)
        nn = tb[sl].shape[0]
        td = np.full(nn, NO_TIME, np.int64)
        out.append(SampleBatch(name, np.arange(k, k + nn, dtype=np.int64), tb[sl] + 1000, td, tb[sl], vals[sl]))
    return out


@pytest.mark.parametrize("kind", ["fusion", "madgwick"])
@pytest.mark.parametrize("with_cal", [False, True])
def test_processor_sample_and_batch_outputs_identical(kind: str, with_cal: bool) -> None:
    t, g, a, _, _ = motion(100, 2.0, [0.5, -0.3, 0.7], noise=0.2, seed=4)
    cals = None
    if with_cal:
        cals = {"wrist": ImuCalibration(gyro_bias=(0.01, -0.02, 0.005), acc_offset=(0.1, 0, -0.05),
                                        acc_matrix=((1.01, 0.002, 0), (0, 0.99, 0.001), (0, 0, 1.0)),
                                        mounting=tuple(Rotation.from_euler("y", 30, degrees=True)
                                                       .as_quat(scalar_first=True)),
                                        yaw_offset_rad=0.3)}
    batches = _batches(t, a, g)
    pb = OrientationProcessor([imu_info()], kind, cals)
    outb: list = []
    pb.bind(outb.append)
    for b in batches:
        pb.on_item(b)
    ps = OrientationProcessor([imu_info()], kind, cals)
    outs: list = []
    ps.bind(outs.append)
    for b in batches:
        for s in b.samples():
            ps.on_item(s)
    assert all(type(x) is SampleBatch for x in outb) and all(type(x) is Sample for x in outs)
    for name in ("wrist/orientation", "wrist/gravity", "wrist/linear_acc"):
        vb = np.vstack([x.values for x in outb if x.stream == name])
        vs = np.array([x.values for x in outs if x.stream == name])
        np.testing.assert_array_equal(vb, vs)
        seq_b = np.concatenate([x.seq for x in outb if x.stream == name])
        seq_s = [x.seq for x in outs if x.stream == name]
        np.testing.assert_array_equal(seq_b, np.arange(len(t)))
        assert seq_s == list(range(len(t)))
        # the same three times as the input samples
        np.testing.assert_array_equal(np.concatenate([x.t_bus_ns for x in outb if x.stream == name]),
                                      [s.t_bus_ns for s in outs if s.stream == name])
        assert [s.t_host_ns - s.t_bus_ns for s in outs if s.stream == name] == [1000] * len(t)
        assert all(s.t_device_ns is None for s in outs if s.stream == name)
    assert pb.samples_in == ps.samples_in == pb.samples_out == len(t)


def test_processor_outputs_declared_and_foreign_items_ignored() -> None:
    p = OrientationProcessor([imu_info(), imu_info("ankle/imu", units=("g",) * 3 + ("deg/s",) * 3 + ("degC",))])
    names = [s.name for s in p.output_streams()]
    assert names == ["wrist/orientation", "wrist/gravity", "wrist/linear_acc",
                     "ankle/orientation", "ankle/gravity", "ankle/linear_acc"]
    kinds = {s.name: (s.kind, s.channels, s.units) for s in p.output_streams()}
    assert kinds["wrist/orientation"] == ("orientation", ("w", "x", "y", "z"), ("1",) * 4)
    assert kinds["ankle/gravity"] == ("gravity", ("x", "y", "z"), ("m/s^2",) * 3)
    assert "ENU" in (p.output_streams()[0].frame or "")
    out: list = []
    p.bind(lambda it: (out.append(it), p.on_item(it)))  # outputs fed back (as a bus would) are ignored
    p.on_item(Sample("mouse/pointer", 0, 1, None, 1, (1.0, 2.0)))
    p.on_item(Sample("ankle/imu", 0, 10**9, None, 10**9, (0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 20.0)))
    p.on_item(Sample("ankle/imu", 1, 10**9 + 10**7, None, 10**9 + 10**7, (0.0, 0.0, 1.0, 0.0, 0.0, 90.0, 20.0)))
    assert len(out) == 6 and p.ignored_items == 1 + 6
    # ankle reports g and deg/s: converted to SI before the filter
    assert out[1].values == pytest.approx((0.0, 0.0, G0), abs=1e-6)
    assert p.stats()["samples_out"] == 2 and p.stats()["rejected_inputs"] == 0


def test_processor_counts_gaps_and_rejected() -> None:
    p = OrientationProcessor([imu_info()])
    p.bind(lambda it: None)
    t, g, a, _, _ = motion(100, 1.0, [0, 0, 0])
    t = np.concatenate([t, t[-1] + 2.0 + t[:10]])
    g = np.vstack([g, g[:10]])
    a = np.vstack([a, a[:10]])
    g[5] = np.nan
    for b in _batches(t, a, g, size=7):
        p.on_item(b)
    assert p.gaps_skipped == 1 and p.rejected_inputs == 1


def test_processor_auto_bias_applied_when_confident() -> None:
    # still in three orientations, 6 s each, with a gyro bias: the processor learns and subtracts it
    bias = np.array([0.4, -0.3, 0.2]) * D2R
    parts = []
    for k, rot in enumerate([Rotation.identity(), Rotation.from_euler("x", 90, degrees=True),
                             Rotation.from_euler("y", 90, degrees=True)]):
        t, g, a, _, _ = motion(100, 6.0, [0, 0, 0], q0=rot, noise=0.1, seed=k)
        parts.append((t + 7.0 * k, g + bias, a))
    p = OrientationProcessor([imu_info()], auto_bias=True)
    p.bind(lambda it: None)
    for t, g, a in parts:
        for b in _batches(t, a, g):
            p.on_item(b)
    ab = p.auto_bias("wrist/imu")
    assert ab is not None
    np.testing.assert_allclose(ab, bias, atol=0.03 * D2R)


@pytest.mark.parametrize("kind", ["fusion", "madgwick", "mahony", "ekf"])
def test_a_start_before_the_first_mag_reading_takes_its_heading_from_that_reading(kind):
    """Live, a reading's IMU sample reaches the filter before its magnetometer sample, so the start
    has no heading; the first reading (within a second) re-initialises it instead of the filter
    slowly turning to north over seconds. Still sensor, tilted, facing 60 degrees."""
    r = Rotation.from_euler("ZYX", [60.0, -5.0, 10.0], degrees=True)  # sensor -> ENU
    acc = r.inv().apply([0.0, 0.0, G0])
    mag = r.inv().apply([0.0, 20.0, -45.0])
    f = OrientationFilter(kind)
    heads = []
    for i in range(50):
        t = i / 100
        res = f.update_many([t], [[0.0, 0.0, 0.0]], [acc])
        f.add_mag([t], [mag])
        heads.append(math.degrees(quat_heading(res.q[0])))
    assert abs(heads[0]) < 1e-6  # nothing to take a heading from yet
    assert f.heading_inits == 1
    assert np.allclose(heads[1:], 60.0, atol=1.0), heads[:5]
    # a magnetometer that only turns up after a second does not make the orientation jump
    g = OrientationFilter(kind)
    for i in range(150):
        g.update_many([i / 100], [[0.0, 0.0, 0.0]], [acc])
    g.add_mag([1.5], [mag])
    g.update_many([1.51], [[0.0, 0.0, 0.0]], [acc])
    assert g.heading_inits == 0
