"""Abilities beyond ``Transport`` are declared (``devices.transports.base``), not probed by name:
each simulated transport is the protocols it should be, real transports are none of them, and
``Device.poll`` reads a ``BatchSource`` in batches."""

from __future__ import annotations

import pytest

from capture.errors import EndOfStream
from capture.recorder import SessionRecorder
from capture.sample import DeviceChunk, Sample, SampleBatch
from capture.session import SessionWriter
from devices import open_device
from devices.transports import open_transport
from devices.transports.base import BatchSource, LoopingMotion, RecordedTimeline, SimulatorTruth, Transport
from devices.transports.network import NetTransport
from devices.transports.sensorserver import SensorServerTransport
from sim_devices.motion import WavingMotion

ABILITIES = (BatchSource, RecordedTimeline, SimulatorTruth)


def record_synth(path: str, seconds: float = 1.0) -> None:
    """A one-device session of a synthetic IMU, written without the application layer."""
    d = open_device(f"a=synth://imu?rate=100&realtime=false&duration={seconds}")
    w = SessionWriter(path, fsync=False)
    rec = SessionRecorder(w)
    rec.add_device(d.name, d.kind, d.transport.url, d.device_options, d.identity, d.streams)
    for item in d.open():
        rec.on_item(item)
    try:
        while True:
            for item in d.poll(0.1):
                rec.on_item(item)
    except EndOfStream:
        pass
    rec.stop()


def abilities(t: Transport) -> set[str]:
    return {p.__name__ for p in ABILITIES if isinstance(t, p)}


def test_replay_is_a_batch_source_on_a_recorded_timeline(session_path):
    record_synth(session_path)
    fast = open_transport(f"replay://{session_path}?speed=0")
    paced = open_transport(f"replay://{session_path}?speed=1")
    assert abilities(fast) == abilities(paced) == {"BatchSource", "RecordedTimeline"}
    assert fast.batches and not paced.batches  # the ability is declared; whether it applies now is its state
    assert not open_transport(f"replay://{session_path}?speed=0&stamp=now").batches


def test_simulators_know_the_truth():
    synth = open_transport("synth://imu?drift_ppm=80&latency_ms=2.5&loop_s=1.2&truth=true")
    assert abilities(synth) == {"SimulatorTruth"}
    assert synth.latency_ns == 2_500_000 and synth.drift_ppm == 80.0 and synth.truth_ns == []
    assert isinstance(synth.motion, LoopingMotion) and synth.motion.loop_s == 1.2
    assert synth.motion.mean_loop_s(0.0, 6.0) == pytest.approx(1.2, rel=0.08)
    free = open_transport("synth://imu")
    assert free.motion is not None and free.motion.loop_s is None and free.latency_ns == 1_000_000

    pad = open_transport("simhid://dualsense?drift_ppm=-30&latency_ms=0.5")
    assert abilities(pad) == {"SimulatorTruth"}
    assert pad.latency_ns == 500_000 and pad.drift_ppm == -30.0
    assert isinstance(pad.motion, WavingMotion) and pad.motion.loop_s is None
    mouse = open_transport("simhid://mouse")
    assert abilities(mouse) == {"SimulatorTruth"} and mouse.motion is None


def test_simulated_truth_is_filled_as_readings_are_made():
    d = open_device("synth://imu?rate=100&realtime=false&duration=0.5&truth=true&latency_ms=3")
    d.open()
    n = 0
    try:
        while True:
            n += sum(isinstance(x, Sample) and x.stream.endswith("/imu") for x in d.poll(0.1))
    except EndOfStream:
        pass
    tr = d.transport
    assert isinstance(tr, SimulatorTruth)
    assert len(tr.truth_ns) == n == 50
    assert all(b - a == 10_000_000 for a, b in zip(tr.truth_ns, tr.truth_ns[1:], strict=False))


@pytest.mark.parametrize("url", ["loop://", "serial:///dev/ttyUSB9?baud=115200", "socket://localhost:7777",
                                 "rfc2217://localhost:7777", "hid://054c:0ce6", "net://serve/page/abc",
                                 "sensorserver://10.0.0.2:8080"])
def test_real_transports_declare_no_simulator_or_replay_ability(url):
    t = open_transport(url)
    assert abilities(t) == set()


def test_the_live_network_classes_are_what_the_registry_gives():
    assert type(open_transport("net://serve/page/abc")) is NetTransport
    assert type(open_transport("sensorserver://10.0.0.2:8080")) is SensorServerTransport


def test_poll_reads_a_batch_source_in_batches_only_while_batches_is_on(session_path):
    record_synth(session_path, 2.0)
    fast = open_device(f"replay://{session_path}?speed=0")
    fast.open()
    items = fast.poll(0.1)
    assert any(type(x) is SampleBatch for x in items)
    imu = [x for x in items if type(x) in (Sample, SampleBatch) and x.stream == "a/imu"]
    assert sum(1 if type(x) is Sample else len(x.seq) for x in imu) == 200  # the whole take in one read
    now = open_device(f"replay://{session_path}?speed=0&stamp=now")
    now.open()
    polls = [now.poll(0.1) for _ in range(20)]
    assert all(sum(type(x) is DeviceChunk for x in p) == 1 for p in polls)  # one chunk per poll
    assert {type(x) for p in polls for x in p} & {Sample, SampleBatch} == {Sample}
