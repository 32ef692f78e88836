"""perfcap calibrate and --orientation end to end on pty-served serial IMUs: the stored calibration
is found by device identity, applied while recording, kept across a reconnect, recorded with the
session and re-applied on replay."""

from __future__ import annotations

import json

import numpy as np
import pytest
from cli_helpers import run
from wait_helpers import DEADLINE_S, wait_until

from capture.app.orchestrator import CALIBRATION_KEY, Capture
from capture.app.replay import replay_session
from capture.calibration_store import CalibrationStore
from capture.sample import DeviceIdentity
from capture.session import SessionReader
from devices.base import DeviceState
from devices.reader import ReconnectPolicy
from sim_devices.frames import WavingSource
from sim_devices.serial_sim import PtySerialDevice

BIAS_DPS = (0.8, -0.5, 0.3)


def test_gyro_calibration_is_measured_stored_and_shown(capsys, tmp_path):
    caldir = str(tmp_path / "cal")
    with PtySerialDevice(WavingSource("witmotion", 200.0, seed=1, amplitude_deg=0.0, gyro_bias_dps=BIAS_DPS,
                                      gyro_noise_dps=0.05)) as sim:
        dev = f"wrist=witmotion@serial://{sim.path}?rate=200&device_clock=true"
        code, out, err = run(capsys, "calibrate", "-d", dev, "--gyro", "--seconds", "1.5",
                             "--calibration-dir", caldir, "--json")
    assert code == 0, err
    rep = json.loads(out.strip().splitlines()[-1])
    assert np.allclose(rep["gyro_bias_dps"], BIAS_DPS, atol=0.02)
    assert max(rep["gyro_bias_stderr_dps"]) < 0.02
    cal = CalibrationStore(caldir).load(DeviceIdentity(kind="witmotion", name="wrist", url=""))
    assert cal is not None and np.allclose(np.degrees(cal.gyro_bias), BIAS_DPS, atol=0.02)
    code, out, _ = run(capsys, "calibrate", "--list", "--calibration-dir", caldir)
    assert code == 0 and "witmotion-wrist.json" in out
    code, out, _ = run(capsys, "calibrate", "-d", dev, "--show", "--calibration-dir", caldir)
    assert code == 0 and "gyro_bias" in out


def test_calibrating_a_moving_sensor_is_refused(capsys, tmp_path):
    with PtySerialDevice(WavingSource("witmotion", 200.0, seed=2)) as sim:
        code, _, err = run(capsys, "calibrate", "-d", f"w=witmotion@serial://{sim.path}?rate=200",
                           "--gyro", "--seconds", "1", "--calibration-dir", str(tmp_path))
    assert code == 2 and "error" in err and "still" in err.lower()
    assert not list(tmp_path.glob("*.json"))


def test_damaged_calibration_file_is_a_clear_error(capsys, tmp_path):
    (tmp_path / "witmotion-wrist.json").write_text("{not json")
    code, _, err = run(capsys, "calibrate", "-d", "wrist=witmotion@serial:///dev/ttyNOPE", "--show",
                       "--calibration-dir", str(tmp_path))
    assert code == 2 and "witmotion-wrist.json" in err and "not a perfcap calibration" in err
    code, out, _ = run(capsys, "calibrate", "--list", "--calibration-dir", str(tmp_path))
    assert code == 0 and "DAMAGED" in out


def test_orientation_uses_the_calibration_across_reconnects_and_replay(tmp_path):
    store = CalibrationStore(tmp_path / "cal")
    ident = DeviceIdentity(kind="witmotion", name="wrist", url="")
    from capture.calibration import ImuCalibration
    store.save(ident, ImuCalibration(gyro_bias=tuple(np.radians(BIAS_DPS))), note="test")
    out = str(tmp_path / "take.mcap")
    src = WavingSource("witmotion", 200.0, seed=3, gyro_bias_dps=BIAS_DPS)
    with PtySerialDevice(src) as sim:
        cap = Capture([f"wrist={sim.device_url()}"], output=out, reconnect=ReconnectPolicy(initial_s=0.02, max_s=0.1))
        proc = cap.enable_orientation("fusion", auto_bias=False, store=store)
        assert proc is not None
        cap.start()
        try:
            dev = cap.devices[0]

            def imu_samples() -> int:
                return int(cap.stats.snapshot().get("wrist/imu", {}).get("samples", 0))

            for k in range(2):  # unplugged twice, each time once the reader streams again
                wait_until(lambda n=200 * (k + 1): imu_samples() >= n, DEADLINE_S, "a second of readings")
                sim.unplug()
                wait_until(lambda n=k + 1: sim.stats.unplugs == n and dev.state is not DeviceState.STREAMING,
                           DEADLINE_S, "the reader to see the unplug")
                sim.replug()
                wait_until(lambda n=k + 1: dev.stats.reconnects == n, DEADLINE_S, "the reconnect")
            wait_until(lambda: imu_samples() >= 600, DEADLINE_S, "three seconds of readings")
        finally:
            rep = cap.stop()
    assert rep.devices["wrist"]["reconnects"] == 2
    rd = SessionReader(out)
    doc = json.loads(rd.devices["wrist"].descriptors[CALIBRATION_KEY])
    assert np.allclose(np.degrees(doc["calibration"]["gyro_bias_rad_s"]), BIAS_DPS)
    imu, q = rd.samples("wrist/imu"), rd.samples("wrist/orientation")
    assert len(q) == len(imu) and np.array_equal(q.t_bus_ns, imu.t_bus_ns)
    # every orientation after each reconnect still uses the calibration: roll and pitch follow the truth
    w, x, y, z = q.values.T
    roll = np.degrees(np.arctan2(2 * (w * x + y * z), 1 - 2 * (x * x + y * y)))
    pitch = np.degrees(np.arcsin(np.clip(2 * (w * y - z * x), -1, 1)))
    # the WT901's angle packets carry the simulator's true roll, pitch and yaw for the same readings
    eul = rd.samples("wrist/euler")
    assert np.array_equal(eul.t_bus_ns, q.t_bus_ns)
    eul = eul.values
    settled = q.t_bus_ns > q.t_bus_ns[0] + 1_000_000_000
    err = np.hypot(roll - eul[:, 0], pitch - eul[:, 1])[settled]
    assert np.median(err) < 3.0, np.median(err)  # waving with linear acceleration: about 2 degrees measured
    # replay rebuilds the orientation with the recorded calibration and finds it equal
    r = replay_session(out, speed=0)
    assert r.verification["equal"], r.verification["first_mismatch"]
    assert r.verification["streams"]["wrist/orientation"]["compared"] == len(q)


def test_yaw_reset_makes_the_held_heading_zero_in_later_recordings(capsys, tmp_path):
    """--yaw measures the heading held still (against the simulated earth field) and stores it as the
    yaw offset; a later recording in the same pose then reads heading zero, with roll and pitch kept."""
    from capture.calibration import quat_heading

    caldir = str(tmp_path / "cal")
    src = WavingSource("witmotion", 200.0, seed=4, amplitude_deg=0.0, heading_deg=30.0)
    with PtySerialDevice(src) as sim:
        dev = f"wrist=witmotion@serial://{sim.path}?rate=200&device_clock=true"
        code, out, err = run(capsys, "calibrate", "-d", dev, "--yaw", "--seconds", "2",
                             "--calibration-dir", caldir, "--json")
        assert code == 0, err
        rep = json.loads(out.strip().splitlines()[-1])
        assert abs(rep["yaw_offset_deg"] - 30.0) < 2.0, rep
        take = str(tmp_path / "t.mcap")
        code, _, err = run(capsys, "record", "-q", "-d", dev, "-o", take, "--orientation", "--duration", "2",
                           "--calibration-dir", caldir)
        assert code == 0, err
    q = SessionReader(take).samples("wrist/orientation").values[-100:]
    heading = np.degrees([quat_heading(x) for x in q])
    assert np.all(np.abs(heading) < 2.0), heading
    w, x, y, z = q[-1]
    assert abs(np.degrees(np.arctan2(2 * (w * x + y * z), 1 - 2 * (x * x + y * y))) - 10.0) < 1.0


def test_yaw_reset_needs_a_magnetometer(capsys, tmp_path):
    with PtySerialDevice(WavingSource("witmotion", 200.0, seed=5, amplitude_deg=0.0)) as sim:
        code, _, err = run(capsys, "calibrate", "-d", f"w=witmotion@serial://{sim.path}?rate=200", "--yaw",
                           "--seconds", "0.5", "--calibration-dir", str(tmp_path))
    assert code == 2 and "no magnetometer" in err
    assert not list(tmp_path.glob("*.json"))


def test_replay_orientation_of_a_session_recorded_without_it(tmp_path):
    out = str(tmp_path / "plain.mcap")
    Capture(["wrist=synth://imu?rate=200&realtime=false&duration=2"], output=out).run(None)
    r = replay_session(out, speed=0, orientation=True, output=str(tmp_path / "with.mcap"))
    assert r.verification["equal"]
    q = SessionReader(str(tmp_path / "with.mcap")).samples("wrist/orientation")
    assert len(q) == 400 and np.allclose(np.linalg.norm(q.values, axis=1), 1.0, atol=1e-6)


@pytest.mark.parametrize("flag", ["--orientation", "--no-orientation"])
def test_record_orientation_flag(capsys, tmp_path, flag):
    out = str(tmp_path / "t.mcap")
    code, _, err = run(capsys, "record", "-q", "-d", "wrist=synth://imu?rate=100&realtime=false&duration=1",
                       "-o", out, flag, "--calibration-dir", str(tmp_path / "none"))
    assert code == 0, err
    assert ("wrist/orientation" in SessionReader(out).streams) == (flag == "--orientation")
