"""The puppet's wiring (``capture.app.puppet_run``): trajectory CSVs read and checked line by line, resampling to
a fixed rate (linear positions, slerped orientations, touch as last set), phone attitude streams turned into
perfcap's Y-up world, touches of several fingers, recorded phone sessions (the page protocol through the real
codec, device, clock sync and recorder), the state timeline and time per state, VMC bundles caught by a real
UDP receiver, send errors counted, and the live ``PuppetFollower`` fed from a real ``SampleBus`` giving the
same frames as the offline path."""

from __future__ import annotations

import dataclasses
import math
import os
import socket
import threading
import time
from types import SimpleNamespace
from typing import TYPE_CHECKING

import numpy as np
import pytest
from wait_helpers import DEADLINE_S

from capture.app.orchestrator import Capture
from capture.app.puppet_input import (
    PhoneTrack,
    attitude_quaternions,
    read_trajectory,
    session_track,
    touch_changes,
    unknown_touch_phases,
)
from capture.app.puppet_run import PuppetFollower, PuppetRun, VmcSender, paced, parse_host_port, probe_writable
from capture.bus import Overflow, SampleBus
from capture.clock import ManualClock
from capture.errors import ConfigError
from capture.quat import quat_conj, quat_mul, quat_rotate
from capture.sample import (
    DeviceIdentity,
    Sample,
    SampleBatch,
    StreamInfo,
)
from capture.session import SessionReader
from retarget.puppet import PhoneInput, PuppetRetargeter
from retarget.vmc import decode_frame

if TYPE_CHECKING:
    from pathlib import Path

HEADER = "t,px,py,pz,qw,qx,qy,qz,touch"


# -- helpers ------------------------------------------------------------------------------------
@pytest.fixture(scope="module")
def touched_session(tmp_path_factory: pytest.TempPathFactory, record_phone_session) -> Path:
    return record_phone_session(tmp_path_factory.mktemp("ph") / "touched.mcap", touch=(1.0, 2.0))


@pytest.fixture(scope="module")
def untouched_session(tmp_path_factory: pytest.TempPathFactory, record_phone_session) -> Path:
    return record_phone_session(tmp_path_factory.mktemp("ph") / "untouched.mcap", duration_s=2.0)


@pytest.fixture(scope="module")
def retargeter() -> PuppetRetargeter:
    return PuppetRetargeter()


def fresh(r: PuppetRetargeter) -> PuppetRetargeter:
    r.reset()
    return r


def write_csv(tmp_path: Path, text: str, name: str = "traj.csv") -> str:
    p = tmp_path / name
    p.write_text(text)
    return str(p)


def walk_csv(fs: float = 50.0) -> str:
    """Released 0.5 s, held still 0.5 s, walking forward at 1.2 m/s for 3 s, released at 5 s, 6 s in all."""
    rows = [HEADER]
    for i in range(int(6 * fs) + 1):
        t = i / fs
        z = 0.0 if t < 1.0 else 1.2 * (min(t, 4.0) - 1.0)
        rows.append(f"{t:.4f},0,1.3,{z:.5f},1,0,0,0,{1 if 0.5 <= t < 5.0 else 0}")
    return "\n".join(rows) + "\n"


# -- trajectory CSV -----------------------------------------------------------------------------
def test_trajectory_resampled_linear_positions_slerped_rotations_touch_as_last_set(tmp_path):
    s = math.sqrt(0.5)
    # columns in another order; a 90 degree turn about Y over one second; touch set at 0.51 s
    text = ("touch,t,qw,qx,qy,qz,px,py,pz\n"
            "# the phone turns while it moves\n"
            f"0,0.0,1,0,0,0,0,1,0\n"
            f"1,0.51,{math.cos(math.pi / 4 * 0.51):.12f},0,{math.sin(math.pi / 4 * 0.51):.12f},0,0.51,1,0\n"
            "\n"
            f"1,1.0,{s:.12f},0,{s:.12f},0,1,1,2\n")
    tr = read_trajectory(write_csv(tmp_path, text))
    assert tr.positions is not None and tr.t.tolist() == [0.0, 0.51, 1.0]
    frames = tr.resample(60.0)
    assert len(frames) == 61 and frames[0].t == 0.0 and frames[-1].t == pytest.approx(1.0)
    half = frames[30]
    assert half.t == pytest.approx(0.5)
    # linear position: between 0.0 and 0.51 s, x goes 0 -> 0.51 and z stays 0
    assert half.position == pytest.approx((0.5, 1.0, 0.0))
    # slerp: half a 90 degree turn about Y is 45 degrees
    assert half.quaternion == pytest.approx((math.cos(math.pi / 8), 0.0, math.sin(math.pi / 8), 0.0), abs=1e-9)
    assert [f.touch for f in frames[:32]] == [False] * 31 + [True]   # 0.5 s still released, 0.5167 s held
    assert frames[45].position == pytest.approx((0.51 + 0.49 * (0.75 - 0.51) / 0.49, 1.0, 2.0 * (0.75 - 0.51) / 0.49))


def test_trajectory_without_positions_is_an_imu_only_phone(tmp_path):
    tr = read_trajectory(write_csv(tmp_path, f"{HEADER}\n0,,,,1,0,0,0,1\n0.5,,,,1,0,0,0,1\n"))
    assert tr.positions is None and any("pivot" in n for n in tr.notes)
    assert all(f.position is None and f.touch for f in tr.resample(30.0))


def test_trajectory_quaternions_within_tolerance_are_normalised(tmp_path):
    tr = read_trajectory(write_csv(tmp_path, f"{HEADER}\n0,0,1,0,1.004,0,0,0,0\n1,0,1,0,0.9999,0.0001,0,0,0\n"))
    assert np.linalg.norm(tr.quaternions, axis=1) == pytest.approx([1.0, 1.0])


@pytest.mark.parametrize(("text", "message"), [
    ("", "is empty"),
    ("t,px,py,pz,qw,qx,qy,qz\n0,0,0,0,1,0,0,0\n", "line 1: the columns are t,px,py,pz,qw,qx,qy,qz; expected"),
    ("time,px,py,pz,qw,qx,qy,qz,touch\n0,0,0,0,1,0,0,0,0\n", "expected t,px,py,pz,qw,qx,qy,qz,touch"),
    (f"{HEADER}\n", "a header and no samples"),
    (f"{HEADER}\n0,0,1,0,1,0,0,0,0\n0.1,0,1,x,1,0,0,0,0\n", "line 3, column pz: 'x' is not a number"),
    (f"{HEADER}\n0,0,1,0,1,0,0,0,0\n\n0.1,0,1,0,1,0,0,0\n", "line 4: 8 fields where the header has 9"),
    (f"{HEADER}\n0,0,1,0,0,0,0,0,0\n", "line 2: the quaternion (qw,qx,qy,qz) is zero"),
    (f"{HEADER}\n0,0,1,0,1,0,0,0,0\n0.1,0,1,0,1,1,0,0,0\n", "line 3: the quaternion (qw,qx,qy,qz) has norm 1.414"),
    (f"{HEADER}\n0,0,1,0,1,0,0,0,0\n0.1,0,1,0,1,0,0,0,0\n0.1,0,1,0,1,0,0,0,0\n",
     "line 4: time 0.1 s does not increase"),
    (f"{HEADER}\n0.2,0,1,0,1,0,0,0,0\n0.1,0,1,0,1,0,0,0,0\n", "line 3: time 0.1 s does not increase"),
    (f"{HEADER}\n0,0,1,0,1,0,0,0,2\n", "line 2, column touch: '2'; expected 0 or 1"),
    (f"{HEADER}\n0,0,nan,0,1,0,0,0,0\n", "line 2, column py: 'nan' is not a finite number"),
    (f"{HEADER}\n0,0,1,0,1,0,0,0,0\n0.1,,,,1,0,0,0,0\n", "line 3: px,py,pz must be given on every row"),
    (f"{HEADER}\n0,0,1.3,0,1,0,0,0,1\n0.1,1.5e308,1.3,0,1,0,0,0,1\n", "line 3, column px: '1.5e308' m is out of range"),
    (f"{HEADER}\n0,0,1.3,-1e300,1,0,0,0,1\n", "line 2, column pz: '-1e300' m is out of range (positions within"),
])
def test_bad_trajectories_are_one_line_config_errors(tmp_path, text, message):
    path = write_csv(tmp_path, text)
    with pytest.raises(ConfigError) as info:
        read_trajectory(path)
    assert message in str(info.value) and "\n" not in str(info.value)
    assert str(info.value).startswith(path)


def test_positions_up_to_the_bound_are_accepted(tmp_path):
    tr = read_trajectory(write_csv(tmp_path, f"{HEADER}\n0,0,1.3,0,1,0,0,0,1\n0.1,1e5,1.3,-1e5,1,0,0,0,1\n"))
    assert tr.positions is not None and tr.positions[1].tolist() == [1e5, 1.3, -1e5]


@pytest.mark.parametrize(("t", "message"), [
    ([0.0, 1e9], "spans 1e+09 s, 6e+10 frames at 60 Hz; at most 24 h (5184000 frames) is driven"),
    ([0.0, 1e300], "spans 1e+300 s, 6e+301 frames at 60 Hz"),
    ([-1e308, 1e308], "spans inf s"),
    ((np.arange(2000) * 50.0).tolist(), "the times look like milliseconds: write them in seconds"),
])
def test_huge_time_spans_are_config_errors_not_gigabytes(t, message):
    tr = PhoneTrack("traj.csv", np.array(t), np.tile([1.0, 0, 0, 0], (len(t), 1)))
    with pytest.raises(ConfigError) as info:
        tr.resample(60.0)
    assert str(info.value).startswith("traj.csv: the input spans ") and message in str(info.value)
    assert ("milliseconds" in str(info.value)) == (len(t) > 2)
    day = PhoneTrack("day.csv", np.array([0.0, 24 * 3600.0]), np.tile([1.0, 0, 0, 0], (2, 1)))
    assert len(day.frame_times(1.0)) == 24 * 3600 + 1   # 24 h itself is driven


def test_millisecond_times_get_a_note(tmp_path):
    rows = "".join(f"{33 * k},0,1.3,0,1,0,0,0,1\n" for k in range(200))
    tr = read_trajectory(write_csv(tmp_path, f"{HEADER}\n{rows}"))
    assert any("median 33 s: if they are milliseconds, write them in seconds" in n for n in tr.notes)
    assert not any("milliseconds" in n for n in read_trajectory(write_csv(tmp_path, walk_csv(), "w.csv")).notes)


def test_missing_and_directory_inputs(tmp_path):
    with pytest.raises(ConfigError, match="no such file"):
        read_trajectory(str(tmp_path / "nope.csv"))
    with pytest.raises(ConfigError, match="is a directory"):
        read_trajectory(str(tmp_path))
    (tmp_path / "bin.csv").write_bytes(b"\xff\xfe\x00\x81t,px\n")
    with pytest.raises(ConfigError, match="not a text CSV"):
        read_trajectory(str(tmp_path / "bin.csv"))


# -- attitude and touch --------------------------------------------------------------------------
def stream(name: str, kind: str, channels: tuple[str, ...], units: tuple[str, ...]) -> StreamInfo:
    return StreamInfo(name, kind, channels, units, None, DeviceIdentity("phone", "ph"))


EULER = stream("ph/attitude", "euler", ("alpha", "beta", "gamma"), ("deg",) * 3)


def axes(q: np.ndarray) -> np.ndarray:
    """The phone's x, y, z axes in the world."""
    return np.stack([quat_rotate(q, e) for e in np.eye(3)])


def test_deviceorientation_angles_become_the_y_up_world():
    q = attitude_quaternions(EULER, np.array([[0.0, 0.0, 0.0], [90.0, 0.0, 0.0], [0.0, 90.0, 0.0],
                                              [0.0, 0.0, 90.0]]))
    # flat on a table, top to the north: the screen faces up (+Y), the top points north (-Z), right is east (+X)
    assert axes(q[0]) == pytest.approx(np.array([[1, 0, 0], [0, 0, -1], [0, 1, 0]]), abs=1e-12)
    # alpha 90: turned left about the vertical, the top points west (-X)
    assert axes(q[1])[1] == pytest.approx([-1, 0, 0], abs=1e-12)
    assert q[1] == pytest.approx([0.5, -0.5, 0.5, 0.5], abs=1e-12)   # (-90 deg about X) * (90 deg about Z)
    # beta 90: stood upright, the top points up and the screen faces south (+Z)
    assert axes(q[2])[1:] == pytest.approx(np.array([[0, 1, 0], [0, 0, 1]]), abs=1e-12)
    # gamma 90: tilted right about its own y axis, the screen faces east (+X)
    assert axes(q[3])[2] == pytest.approx([1, 0, 0], abs=1e-12)


def test_deviceorientation_matches_scipys_intrinsic_zxy():
    from scipy.spatial.transform import Rotation

    from capture.app.puppet_input import Z_UP_TO_Y_UP

    ang = np.random.default_rng(1).uniform([0, -180, -90], [360, 180, 90], (300, 3))
    ref = quat_mul(Z_UP_TO_Y_UP, Rotation.from_euler("ZXY", ang, degrees=True).as_quat()[:, [3, 0, 1, 2]])
    got = attitude_quaternions(EULER, ang)
    assert np.abs(np.abs(np.sum(got * ref, axis=1)) - 1.0).max() < 1e-12


ANDROID = stream("hi/attitude", "euler", ("azimuth", "pitch", "roll"), ("deg",) * 3)


def test_android_orientation_angles_are_not_read_as_w3c():
    # flat, top to the east: Android azimuth 90 (clockwise from north); W3C alpha -90 (counter-clockwise)
    a = attitude_quaternions(ANDROID, np.array([[90.0, 0.0, 0.0]]))[0]
    w = attitude_quaternions(EULER, np.array([[-90.0, 0.0, 0.0]]))[0]
    assert abs(float(np.dot(a, w))) == pytest.approx(1.0, abs=1e-12)
    assert axes(a)[1] == pytest.approx([1, 0, 0], abs=1e-12)       # the top points east (+X)
    assert axes(a)[2] == pytest.approx([0, 1, 0], abs=1e-12)       # the screen faces up
    # the same pose drives the puppet the same way: same heading on the retargeter
    r = PuppetRetargeter()
    f_a = r.step(PhoneInput(0.0, tuple(a.tolist()), True, None))
    r.reset()
    f_w = r.step(PhoneInput(0.0, tuple(w.tolist()), True, None))
    assert f_a.root_pos == pytest.approx(f_w.root_pos, abs=1e-9)
    assert np.abs(np.abs(np.sum(f_a.rotations * f_w.rotations, axis=-1)) - 1.0).max() < 1e-9
    # top tilted down (Android pitch +30) is W3C beta -30; left edge up (roll +20) is gamma +20
    assert attitude_quaternions(ANDROID, np.array([[0.0, 30.0, 20.0]])) == pytest.approx(
        attitude_quaternions(EULER, np.array([[0.0, -30.0, 20.0]])), abs=1e-12)


def test_android_angles_match_sensormanager_get_orientation():
    """Android's getOrientation(R): azimuth = atan2(R[1], R[4]), pitch = asin(-R[7]), roll = atan2(-R[6], R[8])
    of the device-to-ENU matrix R; the angles must give back R (in the Y-up world)."""
    from scipy.spatial.transform import Rotation

    from capture.app.puppet_input import Z_UP_TO_Y_UP

    rot = Rotation.random(300, random_state=3)
    m = rot.as_matrix().reshape(-1, 9)
    ang = np.stack([np.arctan2(m[:, 1], m[:, 4]), np.arcsin(-m[:, 7]), np.arctan2(-m[:, 6], m[:, 8])], axis=1)
    ref = quat_mul(Z_UP_TO_Y_UP, rot.as_quat()[:, [3, 0, 1, 2]])
    rad = stream("hi/attitude", "euler", ("azimuth", "pitch", "roll"), ("rad",) * 3)
    for info, v in ((rad, ang), (ANDROID, np.degrees(ang))):
        got = attitude_quaternions(info, v)
        assert np.abs(np.abs(np.sum(got * ref, axis=1)) - 1.0).max() < 1e-12


@pytest.mark.parametrize("channels", [("roll", "pitch", "yaw"), ("pitch", "roll", "yaw"), ("x", "y", "z")])
def test_euler_channels_of_no_known_convention(channels):
    info = stream("ph/attitude", "euler", channels, ("deg",) * 3)
    with pytest.raises(ConfigError) as exc:
        attitude_quaternions(info, np.zeros((1, 3)))
    assert f"euler angles {', '.join(channels)} are of no known convention" in str(exc.value)
    assert "alpha, beta, gamma (W3C) or azimuth, pitch, roll (Android)" in str(exc.value)
    run = PuppetRun(PuppetRetargeter(), rate=10.0)
    with pytest.raises(ConfigError, match="no known convention"):
        PuppetFollower("ph", info, run)


def test_radian_euler_quaternion_channels_by_name_and_missing_values():
    rad = stream("ph/attitude", "euler", ("alpha", "beta", "gamma"), ("rad",) * 3)
    assert attitude_quaternions(rad, np.array([[math.pi / 2, 0, 0]])) == pytest.approx(
        attitude_quaternions(EULER, np.array([[90.0, 0, 0]])))
    xyzw = stream("sl/attitude", "quat", ("x", "y", "z", "w"), ("1",) * 4)
    wxyz = stream("sl/attitude", "quat", ("w", "x", "y", "z"), ("1",) * 4)
    v = np.array([[0.1, 0.2, 0.3, 0.9]])
    assert attitude_quaternions(xyzw, v) == pytest.approx(attitude_quaternions(wxyz, v[:, [3, 0, 1, 2]]))
    got = attitude_quaternions(wxyz, np.array([[0.0, 0, 0, 0], [2.0, 0, 0, 0], [math.nan, 0, 0, 1]]))
    assert np.isnan(got[0]).all() and np.isnan(got[2]).all()
    assert got[1] == pytest.approx([math.sqrt(0.5), -math.sqrt(0.5), 0, 0])   # normalised, then the world turn
    assert attitude_quaternions(EULER, np.array([[math.nan, 10.0, 0.0]])).shape == (1, 4)
    with pytest.raises(ConfigError, match="is not an attitude"):
        attitude_quaternions(stream("ph/imu", "imu", ("ax", "ay", "az"), ("m/s^2",) * 3), np.zeros((1, 3)))


def test_touch_held_while_any_finger_is_down():
    rows = np.array([[0, 1], [0, 2], [1, 2], [2, 1], [1, 2], [3, 2], [1, 5], [2, 5]], float)
    t, held = touch_changes(np.arange(8) * 0.1, np.hstack([rows, np.zeros((8, 5))]))
    assert held.tolist() == [True, True, True, True, True, False, True, False]   # a move counts as down
    assert t.tolist() == pytest.approx(np.arange(8) * 0.1)


def test_touch_rows_with_unknown_phases_are_counted():
    rows = np.array([[0, 1], [7, 1], [math.nan, 1], [-1, 2], [2, 1], [3.5, 1]], float)
    _, held = touch_changes(np.arange(6.0), rows)
    assert held.tolist() == [True, True, True, True, False, False]
    assert unknown_touch_phases(rows) == 4
    assert unknown_touch_phases(rows[:1]) == 0 and unknown_touch_phases(rows[:, ::-1], ("id", "phase")) == 4


def test_single_finger_touch_streams_have_no_id():
    # SensorServer's touch view: (phase, x, y); a finger moving must not count as several fingers
    rows = np.array([[0, 10, 10], [1, 20, 25], [1, 30, 40], [2, 30, 40], [0, 5, 5], [2, 5, 6]], float)
    _, held = touch_changes(np.arange(6.0), rows, ("phase", "x", "y"))
    assert held.tolist() == [True, True, True, False, True, False]
    with pytest.raises(ConfigError, match="needs a phase channel"):
        touch_changes(np.arange(6.0), rows, ("x", "y", "z"))


def test_follower_of_a_quaternion_phone_with_single_finger_touches(retargeter):
    """A SensorServer-style phone (rotation vector quaternions, touches without ids) on a real bus."""
    ident = DeviceIdentity("sensorserver", "ss")
    att = StreamInfo("ss/attitude", "quat", ("w", "x", "y", "z"), ("1",) * 4, 50.0, ident)
    touch = StreamInfo("ss/touch", "touch", ("phase", "x", "y"), ("1", "px", "px"), None, ident)
    run = PuppetRun(fresh(retargeter), rate=50.0)
    follower = PuppetFollower.for_device("ss", [att, touch], run)
    assert not follower.hold
    bus = SampleBus()
    bus.subscribe(follower, policy=Overflow.NEVER_DROP)
    t0 = 5 * 10**9
    for k in range(101):   # 2 s at 50 Hz, turning slowly about the vertical (Z up in the phone's world)
        a = 0.2 * k / 100
        if k in (25, 30, 35, 75):   # down at 0.5 s, moves, up at 1.5 s (just before that attitude sample)
            phase = {25: 0.0, 30: 1.0, 35: 1.0, 75: 2.0}[k]
            bus.publish(Sample("ss/touch", k, 0, None, t0 + k * 20_000_000 + 1_000, (phase, 100.0 + k, 200.0)))
        bus.publish(Sample("ss/attitude", k, 0, None, t0 + k * 20_000_000 + 3_000,
                           (math.cos(a), 0.0, 0.0, math.sin(a))))
    bus.close()
    assert run.frames == 101 and follower.touches == 4 and follower.errors == 0
    assert run.timeline() == [{"t": 0.0, "state": "RELEASED"}, {"t": 0.5, "state": "LOCOMOTION"},
                              {"t": 1.5, "state": "RELEASED"}]


# -- sessions -------------------------------------------------------------------------------------
class FakeReader:
    """A session reader's interface (path, streams, samples) over arrays, for samples a real phone
    rarely sends."""

    def __init__(self, streams: dict[str, tuple[StreamInfo, list[int], list[list[float]]]]) -> None:
        self.path = "fake.mcap"
        self.streams = {n: s for n, (s, _, _) in streams.items()}
        self._data = {n: SimpleNamespace(t_bus_ns=np.array(t, np.int64), values=np.array(v, np.float64))
                      for n, (_, t, v) in streams.items()}

    def samples(self, name: str) -> SimpleNamespace:
        return self._data[name]


def test_session_track_counts_unordered_attitude_and_unknown_touch_phases():
    ident = DeviceIdentity("phone", "ph")
    att = StreamInfo("ph/attitude", "euler", ("alpha", "beta", "gamma"), ("deg",) * 3, 20.0, ident)
    touch = StreamInfo("ph/touch", "touch", ("phase", "id"), ("1", "1"), None, ident)
    t_att = [0, 50, 100, 100, 80, 150, 200, 120, 250]                     # a repeat and two late samples (ms)
    vals = [[0.0, 10.0, 0.0]] * 4 + [[math.nan, 0.0, 0.0]] + [[0.0, 10.0, 0.0]] * 4   # one without values
    reader = FakeReader({
        "ph/attitude": (att, [t * 1_000_000 for t in t_att], vals),
        "ph/touch": (touch, [60_000_000, 70_000_000, 90_000_000, 200_000_000], [[0, 1], [9, 1], [-1, 1], [2, 1]]),
    })
    tr = session_track(reader)
    assert tr.t.tolist() == [0.0, 0.05, 0.1, 0.15, 0.2, 0.25]
    assert "1 attitude sample(s) without values skipped" in tr.notes
    assert "2 attitude sample(s) out of order or at a repeated time skipped" in tr.notes
    assert ("2 touch row(s) of ph/touch with a phase other than 0-3 (start, move, end, cancel) ignored"
            in tr.notes)
    assert tr.touch.tolist() == [True, True, True, False]


def test_follower_counts_unknown_touch_phases(retargeter):
    ident = DeviceIdentity("phone", "ph")
    att = StreamInfo("ph/attitude", "quat", ("w", "x", "y", "z"), ("1",) * 4, 50.0, ident)
    touch = StreamInfo("ph/touch", "touch", ("phase", "id"), ("1", "1"), None, ident)
    run = PuppetRun(fresh(retargeter), rate=50.0)
    follower = PuppetFollower.for_device("ph", [att, touch], run)
    bus = SampleBus()
    bus.subscribe(follower, policy=Overflow.NEVER_DROP)
    for k in range(20):
        if k in (5, 6, 7):
            bus.publish(Sample("ph/touch", k, 0, None, k * 20_000_000 + 1_000, ({5: 0.0, 6: 4.0, 7: 2.5}[k], 1.0)))
        bus.publish(Sample("ph/attitude", k, 0, None, k * 20_000_000 + 3_000, (1.0, 0.0, 0.0, 0.0)))
    bus.close()
    assert follower.touches == 3 and follower.unknown_touches == 2 and run.frames == 20


def test_session_track_from_a_recorded_page_phone(touched_session):
    reader = SessionReader(str(touched_session))
    tr = session_track(reader)
    assert tr.positions is None and not tr.held_throughout
    assert tr.t[0] == 0.0 and np.all(np.diff(tr.t) > 0) and 2.8 < tr.duration < 3.0
    assert len(tr.t) == len(reader.samples("phone/attitude").t_bus_ns)   # ~20 Hz deviceorientation
    assert np.linalg.norm(tr.quaternions, axis=1) == pytest.approx(1.0)
    assert tr.touch.tolist() == [True] * 20 + [False]
    assert tr.touch_t[0] == pytest.approx(1.0, abs=0.03) and tr.touch_t[-1] == pytest.approx(2.0, abs=0.03)
    assert session_track(reader, "phone").t.tolist() == tr.t.tolist()


def test_session_without_touches_is_held_throughout(untouched_session):
    tr = session_track(SessionReader(str(untouched_session)))
    assert tr.held_throughout and any("held throughout" in n for n in tr.notes)
    assert all(f.touch for f in tr.resample(60.0))


def test_session_errors(untouched_session, tmp_path):
    reader = SessionReader(str(untouched_session))
    with pytest.raises(ConfigError, match=r"no attitude stream of a device 'pen'; phones with one: phone"):
        session_track(reader, "pen")
    imu = tmp_path / "imu.mcap"
    Capture(["wrist=synth://imu?rate=100&realtime=false&duration=0.5"], output=str(imu)).run(None)
    with pytest.raises(ConfigError, match=r"holds no phone attitude stream .*wrist/imu \(imu\)"):
        session_track(SessionReader(str(imu)))


# -- the run: timeline, clip, VMC -----------------------------------------------------------------
def test_hold_still_walk_release_timeline_and_time_per_state(tmp_path, retargeter):
    run = PuppetRun(fresh(retargeter), rate=60.0).run(read_trajectory(write_csv(tmp_path, walk_csv())).resample(60))
    assert [e["state"] for e in run.timeline()] == ["RELEASED", "LOCOMOTION", "RELEASED"]
    assert [e["t"] for e in run.timeline()] == pytest.approx([0.0, 0.5, 5.0], abs=1 / 60 + 1e-9)
    times = run.state_times()
    assert list(times) == ["RELEASED", "LOCOMOTION"] and sum(times.values()) == pytest.approx(run.duration)
    assert times["LOCOMOTION"] == pytest.approx(4.5, abs=0.02) and run.duration == pytest.approx(6.0)
    clip = run.clip("walk")
    assert clip.fps == 60.0 and clip.n_frames == run.frames == 361
    assert clip.rotations.shape == (361, retargeter.skeleton.n_joints, 4)
    # the character walked: its root moved forward about as far as the phone (3.6 m), then stopped
    assert clip.root_pos[300, 2] - clip.root_pos[60, 2] == pytest.approx(3.6, abs=0.2)
    assert clip.root_pos[-1, 2] == pytest.approx(clip.root_pos[300, 2], abs=0.2)


def test_first_frame_changes_are_the_first_entry_and_instant_changes_are_kept(retargeter):
    run = PuppetRun(fresh(retargeter), rate=10.0)
    run.step(PhoneInput(0.0, (1.0, 0.0, 0.0, 0.0), True, (0.0, 1.3, 0.0)))
    assert run.timeline() == [{"t": 0.0, "state": "LOCOMOTION"}]
    run._change(0.5, "AIRBORNE")
    run._change(0.5, "RAGDOLL")
    assert [e["state"] for e in run.timeline()] == ["LOCOMOTION", "AIRBORNE", "RAGDOLL"]
    with pytest.raises(ValueError, match="no frames"):
        PuppetRun(fresh(retargeter)).clip()


def test_bad_rates():
    for rate in (0.0, -1.0, math.nan, math.inf, 5000.0):
        with pytest.raises(ConfigError, match="--rate"):
            PhoneTrack("x", np.zeros(1), np.array([[1.0, 0, 0, 0]])).resample(rate)


class Receiver:
    """A VMC receiver: a UDP socket on loopback, read by its own thread as datagrams arrive."""

    def __init__(self) -> None:
        self.sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        self.sock.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 1 << 22)  # room while this thread waits
        self.sock.bind(("127.0.0.1", 0))
        self.sock.settimeout(0.05)
        self.port = self.sock.getsockname()[1]
        self.datagrams: list[bytes] = []
        self.done = threading.Event()
        self.thread = threading.Thread(target=self._run, daemon=True)
        self.thread.start()

    def _run(self) -> None:
        while not self.done.is_set():
            try:
                self.datagrams.append(self.sock.recv(65536))
            except TimeoutError:
                continue

    def wait_for(self, n: int, timeout: float = DEADLINE_S) -> list[bytes]:
        """Stop once ``n`` datagrams came (the tests compare with what the sender counted as sent)."""
        deadline = time.monotonic() + timeout
        while len(self.datagrams) < n and time.monotonic() < deadline:
            time.sleep(0.01)
        self.done.set()
        self.thread.join()
        self.sock.close()
        return list(self.datagrams)


@pytest.fixture
def receiver():
    r = Receiver()
    yield r
    if not r.done.is_set():
        r.wait_for(0, 0.0)


def test_vmc_bundles_reach_a_real_udp_receiver(tmp_path, retargeter, receiver):
    vmc = VmcSender(f"127.0.0.1:{receiver.port}", retargeter.skeleton)
    track = read_trajectory(write_csv(tmp_path, walk_csv(25.0)))
    run = PuppetRun(fresh(retargeter), rate=30.0, vmc=vmc, keep_frames=False)
    frames = []
    for inp in track.resample(30.0):
        frames.append(run.step(inp))
    vmc.close()
    got = [decode_frame(d) for d in receiver.wait_for(len(frames))]
    assert len(got) == len(frames) == run.frames == vmc.sent and vmc.errors == 0
    sk = retargeter.skeleton
    names = [sk.unity_names[n] for n in sk.names if n in sk.unity_names]
    assert all(list(g.bones) == names for g in got)
    assert [g.t for g in got] == pytest.approx([f.t for f in frames], abs=1e-5)
    k = 100   # 3.3 s: walking
    f = frames[k]
    # Unity axes: x mirrored, quaternions (x, -y, -z, w); the root is the hips' ground point
    assert got[k].root[:3] == pytest.approx((-f.root_pos[0], 0.0, f.root_pos[2]), abs=1e-5)
    w, x, y, z = f.rotations[sk.index("LeftUpperLeg")]
    assert got[k].bones["LeftUpperLeg"][3:] == pytest.approx((x, -y, -z, w), abs=1e-6)
    assert got[k].bones["LeftUpperLeg"][:3] == pytest.approx(
        tuple(sk.offsets[sk.index("LeftUpperLeg")] * (-1, 1, 1)), abs=1e-6)
    with pytest.raises(ValueError, match="not kept"):
        run.clip()


def from_unity(v: tuple[float, ...]) -> tuple[np.ndarray, np.ndarray]:
    """A VMC pose (Unity: px py pz qx qy qz qw) back in perfcap's axes: position, (w, x, y, z)."""
    return np.array([-v[0], v[1], v[2]]), np.array([v[6], v[3], -v[4], -v[5]])


def test_vmc_root_is_the_ground_point_and_the_hips_turn_once(retargeter, receiver):
    """Root * Hips recomposes the hips' world pose (a receiver applying the root turns the character
    once, not twice), and the root stands on the ground with a heading only."""
    sk = retargeter.skeleton
    vmc = VmcSender(f"127.0.0.1:{receiver.port}", sk)
    run = PuppetRun(fresh(retargeter), rate=30.0, vmc=vmc, keep_frames=False)
    s = math.sqrt(0.5)
    frames = [run.step(PhoneInput(k / 30, (s, 0.0, s, 0.0) if k > 15 else (1.0, 0.0, 0.0, 0.0), True,
                                  (0.0, 1.3, 0.02 * k))) for k in range(60)]   # turned to +X (90 degrees)
    # and a hips pose with every kind of rotation: heading 120 degrees, pitched and rolled
    from scipy.spatial.transform import Rotation

    q = Rotation.from_euler("YXZ", [120, 25, -15], degrees=True).as_quat()[[3, 0, 1, 2]]
    rot = np.array(frames[-1].rotations, np.float64)
    rot[0] = q
    frames.append(dataclasses.replace(frames[-1], rotations=rot, root_pos=np.array([0.4, 0.8, -2.0])))
    assert vmc.send(frames[-1])
    vmc.close()
    got = [decode_frame(d) for d in receiver.wait_for(len(frames))]
    assert len(got) == len(frames) and vmc.errors == 0
    for f, g in zip(frames, got, strict=True):
        root_p, root_q = from_unity(g.root)
        hips_p, hips_q = from_unity(g.bones["Hips"])
        pos, world = sk.fk(f.root_pos, f.rotations, world_rotations=True)
        assert root_p[1] == 0.0 and root_p[[0, 2]] == pytest.approx(pos[0][[0, 2]], abs=1e-5)
        assert root_q[[1, 3]] == pytest.approx([0.0, 0.0], abs=1e-7)                # a heading about +Y only
        assert root_p + quat_rotate(root_q, hips_p) == pytest.approx(pos[0], abs=1e-5)
        assert abs(float(np.dot(quat_mul(root_q, hips_q), world[0]))) == pytest.approx(1.0, abs=1e-6)
        # the other bones are unchanged: local rotations as the frame's
        w, x, y, z = f.rotations[sk.index("Spine")]
        assert g.bones["Spine"][3:] == pytest.approx((x, -y, -z, w), abs=1e-6)
    # the tilted hips: the root carries the 120 degree heading, the hips only their pitch and roll
    root_q, hips_q = from_unity(got[-1].root)[1], from_unity(got[-1].bones["Hips"])[1]
    assert abs(root_q[0]) == pytest.approx(math.cos(math.radians(60)), abs=1e-6)
    tilt = Rotation.from_quat(hips_q[[1, 2, 3, 0]]).as_euler("YXZ", degrees=True)
    assert tilt == pytest.approx([0.0, 25.0, -15.0], abs=1e-4)
    assert quat_mul(quat_conj(root_q), q) == pytest.approx(hips_q, abs=1e-6) or quat_mul(
        quat_conj(root_q), q) == pytest.approx(-hips_q, abs=1e-6)


def test_vmc_send_errors_are_counted_not_raised(retargeter):
    vmc = VmcSender("255.255.255.255:39539", retargeter.skeleton)   # broadcast without SO_BROADCAST: refused
    run = PuppetRun(fresh(retargeter), rate=10.0, vmc=vmc)
    for k in range(5):
        run.step(PhoneInput(k / 10, (1.0, 0.0, 0.0, 0.0), False, None))
    vmc.close()
    assert (vmc.sent, vmc.errors, run.frames) == (0, 5, 5)
    assert vmc.first_error is not None and "\n" not in vmc.first_error


@pytest.mark.parametrize(("text", "want"), [("127.0.0.1:39539", ("127.0.0.1", 39539)),
                                            ("[::1]:9000", ("::1", 9000)), ("localhost:1", ("localhost", 1))])
def test_host_port(text, want):
    assert parse_host_port(text) == want


@pytest.mark.parametrize("text", ["nohost", ":123", "host:", "host:0", "host:70000", "::1:9000", "host:abc", "",
                                  "localhost:\u00b2", "localhost:\u0663\u0663", "localhost:\uff19\uff10"])
def test_bad_host_port(text, retargeter):
    with pytest.raises(ConfigError, match="--vmc expects HOST:PORT"):
        VmcSender(text, retargeter.skeleton)


def test_probe_writable_leaves_files_as_they_were(tmp_path):
    new = tmp_path / "new.bvh"
    probe_writable(str(new), "-o")
    assert not new.exists()
    old = tmp_path / "old.bvh"
    old.write_text("keep me")
    probe_writable(str(old), "-o")
    assert old.read_text() == "keep me"
    probe_writable(None, "-o")
    if os.path.isdir("/proc"):
        with pytest.raises(ConfigError, match=r"^-o /proc/perfcap-x\.bvh: cannot write it \("):
            probe_writable("/proc/perfcap-x.bvh", "-o")


def test_unresolvable_vmc_host(retargeter):
    with pytest.raises(ConfigError, match=r"cannot resolve 'no-such-host\.invalid'"):
        VmcSender("no-such-host.invalid:9000", retargeter.skeleton)


# -- live: the follower on a real bus --------------------------------------------------------------
def publish_session(bus: SampleBus, reader: SessionReader, names: list[str], batch: int = 4) -> None:
    """Publish a session's samples in bus-time order, a few at a time, as a device reader would."""
    rows = []
    for name in names:
        b = reader.samples(name)
        rows += [(int(t), name, k) for k, t in enumerate(b.t_bus_ns.tolist())]
    rows.sort()
    batches = {name: reader.samples(name) for name in names}
    for i in range(0, len(rows), batch):
        for _, name, k in rows[i:i + batch]:
            b = batches[name]
            bus.publish(SampleBatch(name, b.seq[k:k + 1], b.t_host_ns[k:k + 1], b.t_device_ns[k:k + 1],
                                    b.t_bus_ns[k:k + 1], b.values[k:k + 1]))


def test_follower_on_a_sample_bus_gives_the_offline_frames(touched_session, retargeter):
    reader = SessionReader(str(touched_session))
    offline = PuppetRun(fresh(retargeter), rate=60.0).run(session_track(reader).resample(60.0))
    off_clip, off_timeline = offline.clip(), offline.timeline()

    live_retargeter = PuppetRetargeter(skeleton=retargeter.skeleton, clips=retargeter.clips)
    run = PuppetRun(live_retargeter, rate=60.0)
    follower = PuppetFollower.for_device("phone", list(reader.streams.values()), run)
    assert not follower.hold and follower.attitude.name == "phone/attitude"
    bus = SampleBus()
    bus.subscribe(follower, policy=Overflow.NEVER_DROP, name="puppet")
    publish_session(bus, reader, ["phone/imu", "phone/attitude", "phone/touch"])
    bus.close()
    assert follower.errors == 0 and follower.touches == 21
    assert follower.samples == len(reader.samples("phone/attitude").t_bus_ns)
    assert run.frames == offline.frames
    assert [e["state"] for e in run.timeline()] == [e["state"] for e in off_timeline]
    assert [e["t"] for e in run.timeline()] == pytest.approx([e["t"] for e in off_timeline], abs=1e-6)
    # released until the finger comes down at 1 s (what follows is the retargeter's: the waving phone)
    assert off_timeline[:2] == [{"t": 0.0, "state": "RELEASED"}, {"t": pytest.approx(1.0, abs=0.03),
                                                                 "state": "LOCOMOTION"}]
    live_clip = run.clip()
    assert np.abs(live_clip.root_pos - off_clip.root_pos).max() < 1e-6
    assert np.abs(np.abs(np.sum(live_clip.rotations * off_clip.rotations, axis=-1)) - 1.0).max() < 1e-6


def test_follower_without_touch_stream_holds_and_needs_an_attitude(untouched_session, retargeter):
    reader = SessionReader(str(untouched_session))
    streams = [s for s in reader.streams.values() if s.name != "phone/touch"]
    run = PuppetRun(fresh(retargeter), rate=30.0)
    follower = PuppetFollower.for_device("phone", streams, run)
    assert follower.hold
    bus = SampleBus()
    bus.subscribe(follower, policy=Overflow.NEVER_DROP)
    publish_session(bus, reader, ["phone/attitude"], batch=7)
    bus.close()
    assert run.timeline()[0]["state"] == "LOCOMOTION"   # grabbed from the first frame
    assert run.frames == math.floor(session_track(reader).duration * 30 + 1e-9) + 1
    with pytest.raises(ConfigError, match="has no attitude stream"):
        PuppetFollower.for_device("phone", [s for s in streams if not s.name.endswith("attitude")], run)


def test_follower_as_a_processor_puts_the_pose_stream_on_the_bus(untouched_session, retargeter):
    # the live path: the follower added as a processor publishes <device>/puppet, one sample per frame at
    # the frame's bus time, root then local rotations, equal to the frames it stepped
    from capture.bus import Subscriber

    class Keep(Subscriber):
        def __init__(self) -> None:
            self.items: list = []

        def on_item(self, item) -> None:
            if item.stream == "phone/puppet":
                self.items.append(item)

    reader = SessionReader(str(untouched_session))
    run = PuppetRun(fresh(retargeter), rate=60.0)
    follower = PuppetFollower.for_device("phone", list(reader.streams.values()), run)
    (pose,) = follower.output_streams()
    n = retargeter.skeleton.n_joints
    assert pose.name == "phone/puppet" and pose.kind == "pose" and len(pose.channels) == 3 + 4 * n
    assert pose.channels[:4] == ("root.x", "root.y", "root.z", f"{retargeter.skeleton.names[0]}.w")
    bus = SampleBus()
    keep = Keep()
    bus.subscribe(keep, policy=Overflow.NEVER_DROP)
    follower.bind(bus.publish)
    bus.subscribe(follower, policy=Overflow.NEVER_DROP)
    publish_session(bus, reader, ["phone/attitude"], batch=5)
    bus.close()
    assert len(keep.items) == run.frames == follower.published > 100
    clip = run.clip()
    values = np.array([s.values for s in keep.items])
    np.testing.assert_array_equal(values[:, :3], clip.root_pos)
    rot = values[:, 3:].reshape(-1, n, 4)                   # the clip holds them normalised
    np.testing.assert_allclose(np.abs(np.sum(rot * clip.rotations, axis=-1)), 1.0, atol=1e-9)
    t = np.array([s.t_bus_ns for s in keep.items])
    np.testing.assert_allclose(np.diff(t), 1e9 / 60, atol=1)
    assert [s.seq for s in keep.items] == list(range(len(keep.items)))


@pytest.mark.parametrize("seed", range(20))
def test_paced_frames_go_at_their_own_times_and_none_is_skipped(seed):
    """``paced`` on a manual clock: each frame leaves when the clock has reached the start plus its time since
    the first (rates, offsets and take lengths drawn at random; a frame already late goes at once)."""
    rng = np.random.default_rng(seed)
    rate, t0, n = float(rng.uniform(10, 240)), float(rng.uniform(-5, 5)), int(rng.integers(1, 400))
    frames = [PhoneInput(t0 + i / rate, (1.0, 0.0, 0.0, 0.0), True, None) for i in range(n)]
    clock = ManualClock(start_ns=int(rng.integers(1, 10**12)))
    start = clock.now_ns()
    late_at = int(rng.integers(0, n))
    sent: list[tuple[float, int]] = []
    for i, f in enumerate(paced(frames, clock)):
        sent.append((f.t, clock.now_ns()))
        if i == late_at:
            clock.advance(int(rng.uniform(0, 0.5) * 1e9))  # the sender fell behind here
    assert [t for t, _ in sent] == [f.t for f in frames]
    behind = 0
    for i, (t, at) in enumerate(sent):
        due = start + round((t - t0) * 1e9)
        assert at >= due  # never early
        if i <= late_at:
            assert at == due
        behind = max(behind, at - due)
    assert behind <= 0.5e9  # late ones catch up: no more behind than the stall


def test_the_puppets_pose_stream_is_a_skeleton_in_the_3d_view(retargeter, tmp_path):
    """The follower's pose stream carries its skeleton, so a session (and the live Foxglove server) shows
    the character as one transform per joint from its parent, stood up in Foxglove's Z-up world."""
    import generic_mcap_check
    from mcap.reader import make_reader
    from mcap_protobuf.decoder import DecoderFactory

    from capture.session import SessionWriter

    ident = DeviceIdentity("phone", "ph")
    att = StreamInfo("ph/attitude", "quat", ("w", "x", "y", "z"), ("1",) * 4, 50.0, ident)
    run = PuppetRun(fresh(retargeter), rate=50.0)
    follower = PuppetFollower.for_device("ph", [att], run)
    poses: list[Sample] = []
    follower.bind(poses.append)
    bus = SampleBus()
    bus.subscribe(follower, policy=Overflow.NEVER_DROP)
    for k in range(30):
        bus.publish(Sample("ph/attitude", k, 0, None, k * 20_000_000 + 3_000, (1.0, 0.0, 0.0, 0.0)))
    bus.close()
    assert len(poses) > 20
    path = tmp_path / "pose.mcap"
    w = SessionWriter(str(path), fsync=False)
    w.add_stream(follower.pose)
    w.write_samples(SampleBatch.from_samples(follower.pose.name, poses, len(follower.pose.channels)), 0)
    w.close()
    assert generic_mcap_check.check(path).problems == []
    sk = run.retargeter.skeleton
    with path.open("rb") as f:
        msgs = [d for _, c, _, d in make_reader(f, decoder_factories=[DecoderFactory()]).iter_decoded_messages()
                if c.topic == "/tf/ph/puppet"]
    assert len(msgs) == len(poses)
    tf = msgs[0].transforms
    assert len(tf) == sk.n_joints + 1 and (tf[0].parent_frame_id, tf[0].child_frame_id) == ("world", "ph/puppet")
    for j in range(sk.n_joints):
        p = int(sk.parents[j])
        assert tf[j + 1].child_frame_id == f"ph/puppet/{sk.names[j]}"
        assert tf[j + 1].parent_frame_id == ("ph/puppet" if p < 0 else f"ph/puppet/{sk.names[p]}")
