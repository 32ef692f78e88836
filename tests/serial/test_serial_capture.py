"""Serial IMUs end to end through a pty: the real pyserial transport, codec and device read a
simulated WT901 that is unplugged, replugged, fed garbage, stalled and batched like an FTDI chip.
They run in CI (no hardware).

They hold on a busy machine: the simulator logs every reading it wrote while a reader had the port
open (``sim.sent``) and when it was unplugged, and each test compares that with what was recorded.
Faults are injected when the reader has reached a state (streaming, disconnected, reconnected), not
after a sleep; a take ends once the simulator is quiet and the reader holds the last reading sent.
The deadlines (``DEADLINE_S``) are only reached when something is broken.
"""

from __future__ import annotations

import os
import subprocess
import sys
import time
from typing import TYPE_CHECKING, Any

import numpy as np
import pytest
from wait_helpers import DEADLINE_S, wait_until

from capture.app.orchestrator import Capture
from capture.app.replay import replay_session
from capture.bus import Overflow, Subscriber
from capture.errors import ConfigError, DeviceNotFoundError
from capture.sample import EventKind, Sample
from capture.session import SessionReader
from devices import open_device
from devices.base import DeviceState
from devices.reader import ReconnectPolicy
from devices.transports import open_transport
from sim_devices.frames import SessionSource, WavingSource
from sim_devices.serial_sim import PtySerialDevice

if TYPE_CHECKING:
    from collections.abc import Iterator

RATE = 200.0
START_MS = 12 * 3_600_000
FAST = ReconnectPolicy(initial_s=0.02, max_s=0.1)
QUIET_S = 3600.0  # a stall that outlasts any test: the simulator writes nothing more


def reading_index(t_device_ns: np.ndarray) -> np.ndarray:
    """The simulator's reading number from the WT901 time packet (ms of day, 5 ms apart)."""
    ms = np.asarray(t_device_ns, np.int64) // 1_000_000
    return np.round((ms - START_MS) * RATE / 1000.0).astype(np.int64)


class Received(Subscriber):
    """Counts one stream's samples on the bus and keeps the newest WitMotion reading number."""

    def __init__(self, stream: str) -> None:
        self.stream = stream
        self.count = 0
        self.last_index = -1

    def on_item(self, item: Any) -> None:
        if item.stream != self.stream:
            return
        if type(item) is Sample:
            self.count += 1
            t_dev = item.t_device_ns
        else:
            self.count += len(item)
            t_dev = int(item.t_device_ns[-1]) if len(item) else None
        if t_dev is not None:
            self.last_index = max(self.last_index, int(reading_index(np.array([t_dev]))[0]))


class Take:
    """A capture of one simulated serial device, opened before the simulator starts streaming, so
    every reading the simulator writes is one the reader could get."""

    def __init__(self, sim: PtySerialDevice, path: str, name: str = "wrist", stream: str = "imu") -> None:
        self.sim = sim
        self.name = name
        self.cap = Capture([f"{name}=" + sim.device_url()], output=path, reconnect=FAST)
        self.received = Received(f"{name}/{stream}")
        self.cap.subscribe(self.received, Overflow.NEVER_DROP, name="test-received")
        self.t_started = 0

    def __enter__(self) -> Take:
        self.cap.start()
        try:
            wait_until(lambda: self.device.state is DeviceState.STREAMING, DEADLINE_S, "the reader to open the port")
            self.t_started = time.monotonic_ns()  # the simulator's stream starts after this
            self.sim.start()
        except BaseException:
            self.__exit__()
            raise
        return self

    def __exit__(self, *exc: object) -> None:
        self.cap.stop()
        self.sim.stop()

    @property
    def device(self) -> Any:
        dev = self.cap.device(self.name)
        assert dev is not None
        return dev

    def events(self, kind: EventKind) -> int:
        return sum(e.source == self.name and e.kind is kind for e in list(self.cap.stats.events))

    def wait_sent(self, n: int) -> None:
        """Until the simulator has written ``n`` readings to the reader."""
        wait_until(lambda: len(self.sim.sent) >= n, DEADLINE_S, f"{n} readings written")

    def quiet(self) -> list[tuple[int, int]]:
        """Write out any held burst and stop the simulator's stream; returns everything it sent."""
        stalls = self.sim.stats.stalls
        self.sim.set_burst(0.0)      # flushes what an FTDI-style burst still holds
        self.sim.stall(QUIET_S)      # processed after the flush, in order
        wait_until(lambda: self.sim.stats.stalls > stalls, DEADLINE_S, "the simulator to go quiet")
        return list(self.sim.sent)

    def stop_when_received(self, *, count: int | None = None, index: int | None = None) -> Any:
        """Stop once the reader has ``count`` samples of its stream, or the reading numbered ``index``."""
        r = self.received
        if count is not None:
            wait_until(lambda: r.count >= count, DEADLINE_S, f"{count} samples (have {r.count})")
        if index is not None:
            wait_until(lambda: r.last_index >= index, DEADLINE_S, f"reading {index} (newest {r.last_index})")
        return self.cap.stop()


def test_pty_witmotion_lossless_with_true_values(session_path):
    with Take(PtySerialDevice(WavingSource("witmotion", RATE, seed=3)), session_path) as take:
        take.wait_sent(400)  # 2 s at 200 Hz
        sent = take.quiet()
        rep = take.stop_when_received(count=len(sent))
    assert rep.recorder_error is None
    imu = SessionReader(session_path).samples("wrist/imu")
    got = reading_index(imu.t_device_ns)
    # every reading written arrived, once, in order
    assert got.tolist() == [i for i, _ in sent]
    assert np.all(np.diff(imu.seq) == 1) and np.all(np.diff(got) == 1)
    # the values are the motion the simulator encoded (within the WT901's 16-bit quantisation)
    acc_g, gyro_dps, _ = take.sim.source.motion.at_many(got / RATE)
    assert np.allclose(imu.values[:, 0:3] / 9.80665, acc_g, atol=16 / 32768)
    assert np.allclose(np.degrees(imu.values[:, 3:6]), gyro_dps, atol=2000 / 32768)
    assert rep.devices["wrist"]["checksum_errors"] == 0 and rep.devices["wrist"]["framing_errors"] == 0


def plugged_windows(sent: list[tuple[int, int]], unplugged: list[tuple[int, int | None]]
                    ) -> list[list[tuple[int, int]]]:
    """What the simulator wrote (reading number, host time) in each stretch between two unplugs."""
    cuts = [start for start, _ in unplugged]
    windows: list[list[tuple[int, int]]] = [[] for _ in range(len(cuts) + 1)]
    for i, t in sent:
        windows[int(np.searchsorted(cuts, t))].append((i, t))
    return windows


def test_twenty_unplug_replug_cycles_reconnect_and_lose_only_what_was_unplugged(session_path):
    cycles = 20
    with Take(PtySerialDevice(WavingSource("witmotion", RATE, seed=5)), session_path) as take:
        sim, dev, r = take.sim, take.device, take.received

        def readings_arrive(what: str) -> None:
            """Until the reader holds ten readings more than the simulator had sent so far."""
            take.wait_sent(1)
            mark = sim.sent[-1][0]
            wait_until(lambda: r.last_index >= mark + 10, DEADLINE_S, what)

        for k in range(cycles):
            readings_arrive(f"readings after replug {k}")
            sim.unplug()
            wait_until(lambda n=k + 1: take.events(EventKind.DISCONNECTED) == n, DEADLINE_S, f"unplug {k + 1} seen")
            lost = sim.stats.lost_unplugged
            # readings fall due while the port is gone: they are never sent
            wait_until(lambda n=lost: sim.stats.lost_unplugged >= n + 3, DEADLINE_S, "readings due while unplugged")
            sim.replug()
            wait_until(lambda n=k + 1: dev.stats.reconnects == n, DEADLINE_S, f"reconnect {k + 1}")
        readings_arrive(f"readings after replug {cycles}")  # the last stretch streams too
        sent = take.quiet()
        rep = take.stop_when_received(index=sent[-1][0])
        stats = sim.stats
    assert stats.unplugs == stats.replugs == cycles and len(stats.unplugged_windows) == cycles
    d = rep.devices["wrist"]
    assert d["reconnects"] == cycles and d["state"] == "closed"
    rd = SessionReader(session_path)
    kinds = [e["kind"] for e in rd.events() if e["source"] == "wrist"]
    assert kinds.count("disconnected") == cycles and kinds.count("reconnected") == cycles
    assert "failed" not in kinds
    imu = rd.samples("wrist/imu")
    got_idx = reading_index(imu.t_device_ns)
    got = set(got_idx.tolist())
    # every reading written while the port was plugged arrived, except those written while the reader
    # was still opening the new port (opening flushes its input) and those still in flight when the
    # cable was pulled: in each plugged stretch what arrived is one run, with no hole
    opens = [e["t_host_ns"] for e in rd.events() if e["source"] == "wrist" and e["kind"] == "opened"]
    windows = plugged_windows(sent, stats.unplugged_windows)
    assert len(opens) == len(windows) == cycles + 1
    for w, written in enumerate(windows):
        arrived = [i in got for i, _ in written]
        n = sum(arrived)
        assert n > 0, f"nothing arrived between unplug {w} and {w + 1}"
        first = arrived.index(True)
        assert arrived[first:first + n] == [True] * n, f"a hole inside plugged stretch {w}"
        assert all(t <= opens[w] for _, t in written[:first]), f"lost after the reader had opened, stretch {w}"
    assert all(i in got for i, _ in windows[-1][first:])  # the last stretch ended quietly: nothing in flight
    assert got <= {i for i, _ in sent}
    # every reading lost (unplugged or in flight) shows as a sequence gap of its exact size
    assert np.array_equal(np.diff(imu.seq), np.diff(got_idx))
    gaps = np.diff(imu.seq)
    assert (gaps > 1).sum() == cycles
    assert int((gaps - 1).sum()) == pytest.approx(d["lost_readings"] / 2, abs=2)  # imu+euler counted
    # the same stream names and identity before and after every reconnect
    assert set(rd.streams) == {"wrist/imu", "wrist/euler", "wrist/mag", "wrist/quat"}


def test_garbage_dropped_bytes_and_bursts_are_counted_and_recovered(session_path):
    sim = PtySerialDevice(WavingSource("witmotion", RATE, seed=7), burst_ms=16, burst_bytes=1000, garbage=0.02)
    with Take(sim, session_path) as take:
        take.wait_sent(100)
        sim.drop_bytes(5)
        sim.inject_garbage(40)
        wait_until(lambda: sim.stats.dropped_bytes == 5, DEADLINE_S, "the dropped bytes")
        n = len(sim.sent)
        take.wait_sent(n + 200)
        sent = take.quiet()
        # the last readings may be the ones garbage damaged: wait for the one before them
        rep = take.stop_when_received(index=sent[-1][0] - 2)
    d = rep.devices["wrist"]
    assert d["framing_errors"] + d["checksum_errors"] > 0 and d["skipped_bytes"] > 0
    rd = SessionReader(session_path)
    imu = rd.samples("wrist/imu")
    assert len(imu) > 200
    # bursts: readings arrive in groups that share one arrival time, yet keep distinct device times
    arrivals = np.unique(imu.t_host_ns)
    assert len(arrivals) < 0.5 * len(imu)
    assert np.all(np.diff(imu.t_device_ns) > 0)
    # bus times are spread out again by the device clock, not bunched at the burst arrivals (a few may still
    # share one: a reading is never stamped after it arrived, and a busy machine delays some of the early ones)
    assert np.all(np.diff(imu.t_bus_ns) >= 0)
    assert len(np.unique(imu.t_bus_ns)) >= 0.9 * len(imu) > 1.8 * len(arrivals)
    # every reading damaged by the dropped bytes or garbage is a counted loss, the rest arrived
    got = set(reading_index(imu.t_device_ns).tolist())
    missing = [i for i, _ in sent if i not in got]
    assert len(missing) <= 2 + sim.stats.garbage_bytes  # a reading hit by garbage or the drop may be lost
    assert d["lost_readings"] >= 2 * len([m for m in missing if m < max(got)])  # a gap needs a reading after it


def test_stall_is_late_not_lost(session_path):
    with Take(PtySerialDevice(WavingSource("witmotion", RATE, seed=9)), session_path) as take:
        sim = take.sim
        take.wait_sent(80)
        sim.stall(0.3)
        wait_until(lambda: sim.stats.stalls == 1, DEADLINE_S, "the stall")
        n_before = len(sim.sent)  # every reading written after these was due 0.3 s later than planned
        take.wait_sent(n_before + 80)
        sent = take.quiet()
        rep = take.stop_when_received(index=sent[-1][0])
    assert rep.devices["wrist"]["reconnects"] == 0
    rd = SessionReader(session_path)
    assert not [e for e in rd.events() if e["kind"] in ("disconnected", "reconnected", "failed")]
    imu = rd.samples("wrist/imu")
    got = reading_index(imu.t_device_ns)
    # not lost: every reading arrived, numbered without a gap
    assert got.tolist() == [i for i, _ in sent]
    assert np.all(np.diff(imu.seq) == 1)
    # late: reading k is due k / RATE after the stream started; those after the stall arrived at
    # least 0.3 s after that (a simulator never writes a reading early, however busy the machine)
    late = np.isin(got, [i for i, _ in sent[n_before:]])
    assert late.sum() >= 80
    due_ns = take.t_started + got * int(1e9 / RATE)
    assert np.all(imu.t_host_ns[late] >= due_ns[late] + 300_000_000)


def test_recorded_session_replays_through_a_pty(tmp_path):
    first = str(tmp_path / "a.mcap")
    with Take(PtySerialDevice(WavingSource("witmotion", RATE, seed=11)), first) as take:
        take.wait_sent(200)
        sent = take.quiet()
        take.stop_when_received(count=len(sent))
    a = SessionReader(first).samples("wrist/imu")
    assert len(a) == len(sent)
    src = SessionSource(first, "wrist")
    assert src.kind == "witmotion" and float(src.device_options()["rate"]) == RATE
    second = str(tmp_path / "b.mcap")
    with Take(PtySerialDevice(src), second) as replayed:
        assert replayed.sim.wait(DEADLINE_S), "the recorded bytes were not all sent"
        replayed.stop_when_received(count=len(a))
    b = SessionReader(second).samples("wrist/imu")
    # the same bytes through the same codec and device: the same readings and values
    assert np.array_equal(a.t_device_ns, b.t_device_ns)
    assert np.array_equal(a.values, b.values)
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
        deadline = time.monotonic() + DEADLINE_S
        while len(got) < 7 and time.monotonic() < deadline:
            c = t.read(0.05)
            if c is not None:
                got += c.data
        assert got == b"\x55\x51hello"
    finally:
        t.close()


@pytest.fixture
def sim_serial_cli(tmp_path) -> Iterator[tuple[subprocess.Popen[str], str, str]]:
    """``perfcap sim serial`` in a child process: (the process, its port link, its sent log)."""
    link = str(tmp_path / "ttyWIT")
    sent_log = str(tmp_path / "sent.npy")
    env = {**os.environ, "PYTHONUNBUFFERED": "1"}
    with subprocess.Popen([sys.executable, "-m", "capture.app.cli", "sim", "serial", "--kind", "witmotion",
                           "--rate", "100", "--link", link, "--duration", "600", "--sent-log", sent_log],
                          stdin=subprocess.PIPE, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                          env=env) as sim:
        try:
            yield sim, link, sent_log
        finally:
            if sim.poll() is None:
                sim.kill()


def test_sim_serial_cli_serves_a_port_that_perfcap_record_reads(tmp_path, sim_serial_cli):
    sim, link, sent_log = sim_serial_cli
    assert sim.stdout is not None and sim.stdin is not None and sim.stderr is not None
    path = sim.stdout.readline().strip()
    assert path == link and os.path.islink(link)
    out = str(tmp_path / "take.mcap")
    r = subprocess.run([sys.executable, "-m", "capture.app.cli", "record", "-d",
                        f"wrist=witmotion@serial://{link}?rate=100&device_clock=true", "-o", out,
                        "--duration", "1.5"], capture_output=True, text=True, timeout=300, check=False,
                       env={**os.environ, "PYTHONUNBUFFERED": "1"})
    assert r.returncode == 0, r.stderr
    sim.stdin.write("quit\n")
    sim.stdin.flush()
    assert sim.wait(DEADLINE_S) == 0
    assert "sent" in sim.stderr.read()
    # what perfcap record got is a run of what the simulator wrote while it had the port open (the
    # first readings may be flushed at open, the last in flight when it closed the port)
    sent = np.load(sent_log)[:, 0]
    imu = SessionReader(out).samples("wrist/imu")
    assert len(imu) > 0 and np.all(np.diff(imu.seq) == 1)
    got = np.round((imu.t_device_ns // 1_000_000 - START_MS) / 10.0).astype(np.int64)  # 100 Hz: 10 ms apart
    first = int(np.searchsorted(sent, got[0]))
    assert got.tolist() == sent[first:first + len(got)].tolist()


@pytest.mark.parametrize("kind,rate,stream", [("bno08x_rvc", 100.0, "euler"), ("textline", 200.0, "imu")])
def test_other_serial_kinds_through_a_pty_are_lossless(session_path, kind, rate, stream):
    with Take(PtySerialDevice(WavingSource(kind, rate, seed=2)), session_path, "x", stream) as take:
        take.wait_sent(int(1.5 * rate))
        sent = take.quiet()
        rep = take.stop_when_received(count=len(sent))
    rd = SessionReader(session_path)
    b = rd.samples(f"x/{stream}")
    assert rep.devices["x"]["checksum_errors"] == 0 and rep.devices["x"]["framing_errors"] == 0
    assert len(b) == len(sent)  # every reading written arrived
    assert np.all(np.diff(b.seq) == 1) and np.all(np.diff(b.t_device_ns) > 0)
    # values are the simulated motion: compare with what the source encodes at the device times
    if kind == "textline":
        t_true = np.round(b.t_device_ns / 1e9 * rate) / rate  # the sketch prints millis(), the motion is at k/rate
        assert np.allclose(np.degrees(b.values[:, 3:6]), take.sim.source.sense(t_true)[1], atol=2e-3)
    else:
        roll = b.values[:, 0]
        assert np.all(np.abs(roll) <= 180.0) and np.ptp(roll) > 5.0
