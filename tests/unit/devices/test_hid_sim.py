"""The simulated HID transport and the HID device base: handshakes kept in the session, replay
without hardware, unplug and replug, errors."""

from __future__ import annotations

import numpy as np
import pytest

from capture.app.orchestrator import Capture
from capture.app.replay import replay_session
from capture.clock import ManualClock
from capture.errors import ConfigError, DeviceIOError, DeviceNotFoundError
from capture.session import SessionReader
from devices import open_device
from devices.hid.base import BUS_KEY, REPORT_DESCRIPTOR_KEY
from devices.reader import ReconnectPolicy
from sim_devices.hid_sim import SimHidTransport


def test_unknown_simulated_device_and_options_are_config_errors():
    with pytest.raises(ConfigError, match="known:"):
        SimHidTransport("nosuch")
    with pytest.raises(ConfigError, match="unknown option"):
        open_device("m=hid@simhid://mouse?nosuch=1")


def test_reports_are_paced_on_a_virtual_clock_in_order_with_their_schedule():
    t = SimHidTransport("mouse", {"realtime": False, "truth": True, "duration": 1.0})
    t.open()
    stamps = []
    while True:
        try:
            c = t.read(0.0)
        except Exception:  # EndOfStream at the end of the second
            break
        if c is not None:
            stamps.append(c.t_ns)
    assert len(stamps) == len(t.arrival_ns) > 900
    assert stamps == t.arrival_ns and np.all(np.diff(stamps) >= 0)
    # true times are the device's send times; arrivals add the fixed latency (0.5 ms by default)
    assert np.all(np.asarray(t.arrival_ns) - np.asarray(t.truth_ns) == 500_000)


def test_an_unplugged_device_errors_then_returns():
    t = SimHidTransport("mouse", {"realtime": False, "unplug_at": 0.2, "unplug_for": 0.3})
    t.open()
    with pytest.raises(DeviceIOError, match="unplugged"):
        while True:
            t.read(0.0)
    assert t.present() is False
    assert t.present() is True  # waiting moved the virtual clock past the window
    t.open()
    assert t.read(0.0) is not None or t.read(0.0) is not None


def test_feature_reports_the_device_lacks_are_clear_errors():
    t = SimHidTransport("mouse", {"realtime": False})
    t.open()
    with pytest.raises(DeviceIOError, match="feature report 0x7f"):
        t.get_feature_report(0x7F, 8)
    t.close()
    with pytest.raises(DeviceIOError, match="closed"):
        t.read(0.0)


def test_handshake_and_descriptor_are_kept_and_replay_needs_no_device(tmp_path):
    out = str(tmp_path / "m.mcap")
    rep = Capture(["m=hid@simhid://mouse?realtime=false&duration=2&seed=4"], output=out).run(None)
    assert rep.devices["m"]["state"] in ("finished", "closed"), rep.devices
    r = SessionReader(out)
    desc = r.devices["m"].descriptors
    assert desc[BUS_KEY] == b"usb" and len(desc[REPORT_DESCRIPTOR_KEY]) > 20
    assert len(r.samples("m/pointer")) > 1500
    v = replay_session(out, speed=0)
    assert v.verification["equal"], v.verification["first_mismatch"]


def test_unplug_and_replug_keep_the_stream_and_record_the_gap(tmp_path):
    out = str(tmp_path / "u.mcap")
    cap = Capture(["m=hid@simhid://mouse?realtime=false&duration=3&unplug_at=1&unplug_for=0.5"], output=out,
                  reconnect=ReconnectPolicy(initial_s=0.01, max_s=0.05))
    rep = cap.run(None)
    assert rep.devices["m"]["reconnects"] >= 1
    r = SessionReader(out)
    p = r.samples("m/pointer")
    gaps = np.diff(p.t_bus_ns) / 1e9
    assert gaps.max() > 0.4  # the unplugged half second
    kinds = [e["kind"] for e in r.events() if e["source"] == "m"]
    assert "disconnected" in kinds and "reconnected" in kinds, kinds
    t = cap.devices[0].transport
    assert t.opens == 2
    # both handshakes are in the session; the replay reproduces every sample
    v = replay_session(out, speed=0)
    assert v.verification["equal"], v.verification["first_mismatch"]


def test_a_device_that_is_not_there_at_open_is_not_found():
    t = SimHidTransport("mouse", {"realtime": False, "unplug_at": 0.0001, "unplug_for": 10})
    t.open()  # the first open starts the simulated clock
    t._virtual_ns += 1_000_000
    t.close()
    with pytest.raises(DeviceNotFoundError):
        t.open()


@pytest.mark.parametrize("url", ["pad=simhid://dualsense?realtime=false&duration=2&bus=bluetooth",
                                 "pad=simhid://switchpro?realtime=false&duration=2",
                                 "pad=simhid://ds4?realtime=false&duration=2"])
def test_controller_imu_streams_feed_orientation_fusion(url, tmp_path):
    out = str(tmp_path / "o.mcap")
    cap = Capture([url], output=out)
    assert cap.enable_orientation("fusion", auto_bias=False) is not None
    cap.run(None)
    r = SessionReader(out)
    imu, q, g = r.samples("pad/imu"), r.samples("pad/orientation"), r.samples("pad/gravity")
    assert len(q) == len(imu) > 100 and np.array_equal(q.t_bus_ns, imu.t_bus_ns)
    assert np.allclose(np.linalg.norm(q.values, axis=1), 1.0, atol=1e-6)
    assert np.allclose(np.linalg.norm(g.values, axis=1), 9.80665, atol=1e-3)


def test_a_reader_that_falls_behind_loses_the_oldest_reports_beyond_the_os_buffer_and_counts_them():
    clock = ManualClock()  # real-time pacing on a clock the test moves: the reader is away exactly 100 ms
    t = SimHidTransport("mouse", {"buffer": 10, "truth": True}, clock=clock)
    t.open()
    assert t.read(0.5) is not None
    clock.advance(100_000_000)  # the reader is away for 100 reports at 1 kHz
    got = [t.read(0.0) for _ in range(10)]
    assert all(c is not None for c in got)
    assert t.read(0.0) is None  # nothing more has arrived yet
    assert t.dropped == 100 - 10, t.dropped  # the OS buffer keeps 10
    assert t.sent == len(t.arrival_ns) + t.dropped == 1 + 100
    # the ten kept are the newest, in order, each stamped when it was read (not when it arrived)
    assert [c.t_ns for c in got] == [clock.now_ns()] * 10
    assert got[0].t_ns >= t.arrival_ns[1]
    assert t.arrival_ns[1:] == sorted(t.arrival_ns[1:]) and t.arrival_ns[1] > t.arrival_ns[0] + 80_000_000
    t.close()


def test_a_controller_that_comes_back_over_bluetooth_is_the_same_device_and_replays_equal(tmp_path):
    """Unplugged from USB, reconnected over Bluetooth: the same streams continue (the Bluetooth
    handshake and report format), the session keeps both handshakes, and the replay answers each
    open with what that open read."""
    out = str(tmp_path / "bt.mcap")
    cap = Capture(["pad=dualsense@simhid://dualsense?realtime=false&duration=3&unplug_at=1&unplug_for=0.3"
                   "&replug_bus=bluetooth"], output=out, reconnect=ReconnectPolicy(initial_s=0.01, max_s=0.05))
    rep = cap.run(None)
    assert rep.devices["pad"]["reconnects"] == 1
    r = SessionReader(out)
    assert r.devices["pad"].history[BUS_KEY] == [b"usb", b"bluetooth"]
    imu = r.samples("pad/imu")
    before = imu.t_bus_ns < imu.t_bus_ns[0] + 1_000_000_000
    assert before.sum() > 200 and (~before).sum() > 300  # motion on both sides of the switch
    acc = np.linalg.norm(imu.values[:, 0:3], axis=1)
    assert 5 < np.median(acc[before]) < 15 and 5 < np.median(acc[~before]) < 15  # calibrated on both buses
    v = replay_session(out, speed=0)
    assert v.verification["equal"], v.verification["first_mismatch"]
