"""Record simulated and real-trace devices, replay through the same codecs: samples equal; timing
follows the recording (checked on a manual clock, so no test sleeps)."""

from __future__ import annotations

import itertools

import numpy as np
import pytest
from wait_helpers import DEADLINE_S, wait_until

from capture.app.orchestrator import Capture
from capture.app.replay import replay_session
from capture.app.replay_check import ReplayVerifier
from capture.clock import ManualClock
from capture.errors import ConfigError, EndOfStream, SessionError
from capture.session import SessionReader
from devices import ReconnectPolicy, open_device

FAST = "realtime=false&duration=3"


def record(path, urls, **kw):
    rep = Capture(urls, output=path, fsync=False, **kw).run(None)
    assert rep.recorder_error is None
    return rep


def test_fast_replay_equals_recording(session_path):
    rep = record(session_path, [f"a=synth://imu?rate=200&drift_ppm=80&jitter_ms=2&{FAST}",
                                f"b=synth://imu?rate=100&device_clock=false&burst_ms=16&garbage=0.01&seed=2&{FAST}",
                                f"c=synth://imu?rate=50&start_ms=86399000&seed=3&{FAST}"])
    assert rep.streams["a/imu"]["samples"] == 600
    r = replay_session(session_path, speed=0)
    v = r.verification
    assert v["equal"], v["first_mismatch"]
    assert sum(x["compared"] for x in v["streams"].values()) == sum(s["samples"] for s in rep.streams.values())
    assert r.capture.devices["b"]["checksum_errors"] + r.capture.devices["b"]["framing_errors"] > 0


def test_real_trace_session_replays_equal(session_path, xio_csv):
    record(session_path, [f"x=synth://imu?csv={xio_csv}&realtime=false&jitter_ms=4&burst_ms=16"])
    r = replay_session(session_path, speed=0)
    assert r.verification["equal"]
    assert r.verification["streams"]["x/imu"]["compared"] == 13514


def test_verifier_detects_a_difference(session_path):
    record(session_path, [f"a=synth://imu?{FAST}"])
    rec = SessionReader(session_path).all_samples()
    v = ReplayVerifier(rec)
    b = rec["a/imu"]
    first = next(b.samples())
    v.on_item(first._replace(values=(0.0,) * 7))
    res = v.result()
    assert not res["equal"] and res["streams"]["a/imu"]["mismatches"] == 1 and "seq 0" in res["first_mismatch"]["a/imu"]


def test_replay_transport_paces_by_recorded_time_at_any_speed(session_path):
    record(session_path, [f"a=synth://imu?rate=100&jitter_ms=3&{FAST}"])
    chunks = list(SessionReader(session_path).raw_chunks("a"))
    for speed in (1.0, 4.0, 0.5):
        clk = ManualClock(50_000_000_000)
        d = open_device(f"replay://{session_path}?speed={speed}", clock=clk)
        d.open()
        t = d.transport
        start = t._start
        seen = []
        while True:
            try:
                c = t.read(10.0)
            except EndOfStream:
                break
            seen.append((clk.now_ns(), c))
        assert [c for _, c in seen] == chunks  # same bytes, same recorded stamps
        for now, c in seen:
            assert now == start + int((c.t_ns - chunks[0].t_ns) / speed)
        d.close()


def test_replay_loops_with_increasing_times(session_path):
    record(session_path, ["a=synth://imu?rate=50&realtime=false&duration=1"])
    d = open_device(f"replay://{session_path}?speed=0&loop=true")
    d.open()
    n = len(list(SessionReader(session_path).raw_chunks("a")))
    got = [d.transport.read(0.1) for _ in range(3 * n)]
    ts = [c.t_ns for c in got]
    assert all(b > a for a, b in itertools.pairwise(ts))
    assert [c.data for c in got[:n]] == [c.data for c in got[n:2 * n]]
    d.close()


def test_replay_stamp_now_option(session_path):
    record(session_path, ["a=synth://imu?rate=50&realtime=false&duration=0.5"])
    clk = ManualClock(123_000_000_000)
    d = open_device(f"replay://{session_path}?speed=0&stamp=now", clock=clk)
    d.open()
    assert d.transport.read(0.1).t_ns == 123_000_000_000
    d.close()


def test_replay_url_errors(session_path, tmp_path):
    record(session_path, [f"a=synth://imu?{FAST}", f"b=synth://imu?{FAST}"])
    with pytest.raises(ConfigError, match=r"has 2 devices .*device=NAME"):
        open_device(f"replay://{session_path}")
    with pytest.raises(ConfigError, match="no device 'z'"):
        open_device(f"replay://{session_path}?device=z")
    with pytest.raises(SessionError, match="no such file"):
        open_device(f"replay://{tmp_path}/none.mcap")
    with pytest.raises(ConfigError, match="stamp"):
        open_device(f"replay://{session_path}?device=a&stamp=later")


def test_unplug_and_reconnect_keep_identity_and_record_the_gap(session_path):
    url = "a=synth://imu?rate=200&unplug_at=0.3&unplug_for=0.4"
    cap = Capture([url], output=session_path, fsync=False, reconnect=ReconnectPolicy(initial_s=0.05, max_s=0.1))
    cap.start()
    try:
        dev = cap.devices[0]
        wait_until(lambda: dev.stats.reconnects == 1, DEADLINE_S, "the reconnect")
        n = dev.stats.readings
        wait_until(lambda: dev.stats.readings >= n + 40, DEADLINE_S, "readings after the reconnect")
    finally:
        rep = cap.stop()
    assert rep.devices["a"]["reconnects"] == 1
    r = SessionReader(session_path)
    kinds = [e["kind"] for e in r.events() if e["source"] == "a"]
    assert kinds.index("disconnected") < kinds.index("reconnecting") < kinds.index("reconnected")
    b = r.samples("a/imu")
    # the device clock ran on while it was away: the readings it missed are one gap in the numbering
    steps = np.diff(b.seq)
    assert np.count_nonzero(steps != 1) == 1
    k = int(np.argmax(steps))
    assert steps[k] == round((b.t_device_ns[k + 1] - b.t_device_ns[k]) / 5e6)  # as many as the device made
    assert steps[k] - 1 >= 0.4 * 200  # at least the 0.4 s away (a reader that was behind loses its backlog too)
    gap = np.max(np.diff(b.t_bus_ns)) / 1e9
    assert 0.35 < gap < 0.45
    assert list(r.streams) == ["a/imu", "a/euler", "a/mag", "a/quat"]
    assert replay_session(session_path, speed=0).verification["equal"]
