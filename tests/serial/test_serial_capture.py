"""Serial IMUs end to end through a pty: the real pyserial transport, codec and device read a
simulated WT901 that is unplugged, replugged, fed garbage, stalled and batched like an FTDI chip.
These run in CI (no hardware); the same checks run on a real port with --hil-serial."""

from __future__ import annotations

import os
import subprocess
import sys
import time

import numpy as np
import pytest

from capture.errors import ConfigError, DeviceNotFoundError
from capture.app.orchestrator import Capture
from capture.app.replay import replay_session
from capture.session import SessionReader
from devices import open_device
from devices.base import ReconnectPolicy
from devices.transports import open_transport
from sim_devices.frames import SessionSource, WavingSource
from sim_devices.serial_sim import PtySerialDevice

RATE = 200.0
START_MS = 12 * 3_600_000
FAST = ReconnectPolicy(initial_s=0.02, max_s=0.1)


def reading_index(t_device_ns: np.ndarray) -> np.ndarray:
    """The simulator's reading number from the WT901 time packet (ms of day, 5 ms apart)."""
    ms = np.asarray(t_device_ns, np.int64) // 1_000_000
    return np.round((ms - START_MS) * RATE / 1000.0).astype(np.int64)


def record(sim: PtySerialDevice, path: str, seconds: float, **kw) -> tuple:
    cap = Capture(["wrist=" + sim.device_url()], output=path, reconnect=FAST, **kw)
    rep = cap.run(seconds)
    return rep, SessionReader(path)


def opened_times(events: list[dict]) -> list[int]:
    return [e["t_host_ns"] for e in events if e["source"] == "wrist" and e["kind"] == "opened"]


def test_pty_witmotion_lossless_with_true_values(session_path):
    with PtySerialDevice(WavingSource("witmotion", RATE, seed=3)) as sim:
        rep, rd = record(sim, session_path, 2.0)
    assert rep.recorder_error is None
    imu = rd.samples("wrist/imu")
    got = reading_index(imu.t_device_ns)
    sent = np.array([i for i, _ in sim.sent])
    assert len(sent) >= 350  # 2 s at 200 Hz, less start-up
    t_open = opened_times(rd.events())[0]
    must = {i for i, t in sim.sent if t > t_open}
    assert must <= set(got.tolist()), f"lost {len(must - set(got.tolist()))} readings"
    assert np.all(np.diff(imu.seq) == 1) and np.all(np.diff(got) == 1)
    # the values are the motion the simulator encoded (within the WT901's 16-bit quantisation)
    acc_g, gyro_dps, _ = sim.source.motion.at_many(got / RATE)
    assert np.allclose(imu.values[:, 0:3] / 9.80665, acc_g, atol=16 / 32768)
    assert np.allclose(np.degrees(imu.values[:, 3:6]), gyro_dps, atol=2000 / 32768)
    assert rep.devices["wrist"]["checksum_errors"] == 0 and rep.devices["wrist"]["framing_errors"] == 0


def test_twenty_unplug_replug_cycles_reconnect_and_lose_nothing_outside_the_windows(session_path):
    src = WavingSource("witmotion", RATE, seed=5)
    with PtySerialDevice(src, unplug_every=0.3, unplug_for=0.1) as sim:
        rep, rd = record(sim, session_path, 0.3 * 20 + 0.2)
        unplugs = sim.stats.unplugs
    assert unplugs >= 20
    dev = rep.devices["wrist"]
    assert dev["reconnects"] >= 20 and dev["state"] == "closed"
    ev = rd.events()
    kinds = [e["kind"] for e in ev if e["source"] == "wrist"]
    assert kinds.count("disconnected") >= 20 and kinds.count("reconnected") >= 20
    assert "failed" not in kinds
    got = set(reading_index(rd.samples("wrist/imu").t_device_ns).tolist())
    # every reading written while the reader had the port open arrived
    opens = opened_times(ev)
    windows = sim.stats.unplugged_windows
    missing = []
    for i, t in sim.sent:
        if t > opens[0] and i not in got:
            missing.append((i, t))
    assert not missing, f"{len(missing)} readings lost outside the unplugged windows, first {missing[:3]}"
    # readings lost while unplugged show as sequence gaps, not as silent holes
    imu = rd.samples("wrist/imu")
    gaps = np.diff(imu.seq)
    assert np.all(gaps >= 1) and (gaps > 1).sum() >= 20
    assert int((gaps - 1).sum()) == pytest.approx(dev["lost_readings"] / 2, abs=2)  # imu+euler counted
    assert len(windows) >= 20
    # the same stream names and identity before and after every reconnect
    assert set(rd.streams) == {"wrist/imu", "wrist/euler", "wrist/mag", "wrist/quat"}


def test_garbage_dropped_bytes_and_bursts_are_counted_and_recovered(session_path):
    with PtySerialDevice(WavingSource("witmotion", RATE, seed=7), burst_ms=16, burst_bytes=1000,
                         garbage=0.02) as sim:
        cap = Capture(["wrist=" + sim.device_url()], output=session_path, reconnect=FAST)
        cap.start()
        time.sleep(0.5)
        sim.drop_bytes(5)
        sim.inject_garbage(40)
        time.sleep(1.0)
        rep = cap.stop()
    d = rep.devices["wrist"]
    assert d["framing_errors"] + d["checksum_errors"] > 0 and d["skipped_bytes"] > 0
    rd = SessionReader(session_path)
    imu = rd.samples("wrist/imu")
    assert len(imu) > 200
    # bursts: readings arrive in groups that share one arrival time, yet keep distinct device times
    arrivals = np.unique(imu.t_host_ns)
    assert len(arrivals) < 0.5 * len(imu)
    assert np.all(np.diff(imu.t_device_ns) > 0)
    # bus times are spread out again by the device clock, not bunched at the burst arrivals
    assert len(np.unique(imu.t_bus_ns)) == len(imu)
    # every reading damaged by the dropped bytes is a counted loss, the rest arrived
    got = set(reading_index(imu.t_device_ns).tolist())
    t_open = opened_times(rd.events())[0]
    missing = [i for i, t in sim.sent if t > t_open and i not in got]
    assert len(missing) <= 2 + sim.stats.garbage_bytes  # a reading hit by garbage or the drop may be lost
    assert d["lost_readings"] >= 2 * len([m for m in missing if m < max(got)])


def test_stall_is_late_not_lost(session_path):
    with PtySerialDevice(WavingSource("witmotion", RATE, seed=9)) as sim:
        cap = Capture(["wrist=" + sim.device_url()], output=session_path, reconnect=FAST)
        cap.start()
        time.sleep(0.4)
        sim.stall(0.3)
        time.sleep(0.8)
        rep = cap.stop()
    assert rep.devices["wrist"]["reconnects"] == 0
    imu = SessionReader(session_path).samples("wrist/imu")
    assert np.all(np.diff(imu.seq) == 1)
    host_gap = np.diff(imu.t_host_ns).max() / 1e9
    assert 0.25 < host_gap < 0.6


def test_recorded_session_replays_through_a_pty(tmp_path):
    first = str(tmp_path / "a.mcap")
    with PtySerialDevice(WavingSource("witmotion", RATE, seed=11)) as sim:
        record(sim, first, 1.0)
    a = SessionReader(first).samples("wrist/imu")
    src = SessionSource(first, "wrist")
    assert src.kind == "witmotion" and float(src.device_options()["rate"]) == RATE
    second = str(tmp_path / "b.mcap")
    with PtySerialDevice(src) as sim2:
        cap = Capture(["wrist=" + sim2.device_url()], output=second, reconnect=FAST)
        cap.start()
        assert sim2.wait(5.0)
        time.sleep(0.2)
        cap.stop()
    b = SessionReader(second).samples("wrist/imu")
    common = np.intersect1d(a.t_device_ns, b.t_device_ns)
    assert len(common) >= 0.9 * len(a)
    ia = np.searchsorted(a.t_device_ns, common)
    ib = np.searchsorted(b.t_device_ns, common)
    assert np.array_equal(a.values[ia], b.values[ib])
    assert replay_session(second, speed=0).verification["equal"]


def test_missing_port_vidpid_and_bad_options_are_clear_errors(tmp_path):
    t = open_transport(f"serial://{tmp_path}/nothing")
    with pytest.raises(DeviceNotFoundError, match="not there"):
        t.open()
    t = open_transport("serial://dead:beef")
    with pytest.raises(DeviceNotFoundError, match="no serial port with USB id dead:beef"):
        t.open()
    assert t.present() is False
    with pytest.raises(ConfigError, match="baud"):
        open_device("witmotion@serial:///dev/ttyUSB9?baud=fast")
    with pytest.raises(ConfigError, match="parity"):
        open_device("witmotion@serial:///dev/ttyUSB9?parity=X")


def test_loop_url_handler_round_trip():
    t = open_transport("loop://")
    t.open()
    try:
        tx = t.write(b"\x55\x51hello")
        assert tx.direction.name == "TX"
        got = b""
        for _ in range(10):
            c = t.read(0.05)
            if c is not None:
                got += c.data
            if len(got) >= 7:
                break
        assert got == b"\x55\x51hello"
    finally:
        t.close()


def test_sim_serial_cli_serves_a_port_that_perfcap_record_reads(tmp_path):
    link = str(tmp_path / "ttyWIT")
    env = {**os.environ, "PYTHONUNBUFFERED": "1"}
    with subprocess.Popen([sys.executable, "-m", "capture.app.cli", "sim", "serial", "--kind", "witmotion",
                           "--rate", "100", "--link", link, "--duration", "20"],
                          stdin=subprocess.PIPE, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                          env=env) as sim:
        try:
            path = sim.stdout.readline().strip()
            assert path == link and os.path.islink(link)
            out = str(tmp_path / "take.mcap")
            r = subprocess.run([sys.executable, "-m", "capture.app.cli", "record", "-d",
                                f"wrist=witmotion@serial://{link}?rate=100&device_clock=true", "-o", out,
                                "--duration", "1.5"], capture_output=True, text=True, timeout=60, env=env)
            assert r.returncode == 0, r.stderr
            imu = SessionReader(out).samples("wrist/imu")
            assert 100 <= len(imu) <= 160 and np.all(np.diff(imu.seq) == 1)
            sim.stdin.write("quit\n")
            sim.stdin.flush()
            assert sim.wait(10) == 0
            assert "sent" in sim.stderr.read()
        finally:
            if sim.poll() is None:
                sim.kill()


@pytest.mark.parametrize("kind,rate,stream", [("bno08x_rvc", 100.0, "x/euler"), ("textline", 200.0, "x/imu")])
def test_other_serial_kinds_through_a_pty_are_lossless(session_path, kind, rate, stream):
    with PtySerialDevice(WavingSource(kind, rate, seed=2)) as sim:
        cap = Capture(["x=" + sim.device_url()], output=session_path, reconnect=FAST)
        rep = cap.run(1.5)
        sent = len(sim.sent)
    rd = SessionReader(session_path)
    b = rd.samples(stream)
    assert rep.devices["x"]["checksum_errors"] == 0 and rep.devices["x"]["framing_errors"] == 0
    assert len(b) >= sent - 2 and len(b) >= 0.8 * rate * 1.4  # the last reading or two may be in flight at stop
    assert np.all(np.diff(b.seq) == 1) and np.all(np.diff(b.t_device_ns) > 0)
    # values are the simulated motion: compare with what the source encodes at the device times
    if kind == "textline":
        t_true = np.round(b.t_device_ns / 1e9 * rate) / rate  # the sketch prints millis(), the motion is at k/rate
        assert np.allclose(np.degrees(b.values[:, 3:6]), sim.source.sense(t_true)[1], atol=2e-3)
    else:
        roll = b.values[:, 0]
        assert np.all(np.abs(roll) <= 180.0) and np.ptp(roll) > 5.0
