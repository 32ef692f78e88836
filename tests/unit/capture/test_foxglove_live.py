"""Live to Foxglove (``capture.app.foxglove_live``): a capture's bus on the Foxglove SDK's WebSocket server,
checked from the other end with a WebSocket client speaking the Foxglove WebSocket protocol (JSON
``serverInfo``/``advertise``/``subscribe``; binary message data: opcode 0x01, u32 subscription id, u64 log
time in ns, little-endian, then the payload), its payloads decoded with nothing but the advertised schema
(a ``FileDescriptorSet``) and the protobuf library, and compared with a session recorded from the same
capture at the same time."""

from __future__ import annotations

import base64
import itertools
import json
import re
import socket
import struct
import subprocess
import sys
import time
from typing import TYPE_CHECKING, Any

import pytest
from google.protobuf import descriptor_pb2, descriptor_pool, message_factory
from mcap.reader import make_reader
from wait_helpers import DEADLINE_S
from websockets.exceptions import ConnectionClosed
from websockets.sync.client import ClientConnection, connect

from capture.app.cli import build_parser
from capture.app.foxglove_live import FoxglovePublisher, FoxgloveServer, start, ws_url
from capture.app.orchestrator import Capture
from capture.app.schema import flag_values
from capture.app.serve.config import FOXGLOVE_PORT, ServeConfig
from capture.bus import Overflow, SampleBus
from capture.errors import ConfigError
from capture.sample import DeviceEvent, DeviceIdentity, EventKind, Sample, StreamInfo
from capture.session import SessionReader
from capture.session_view import LOG_TOPIC, sample_view

if TYPE_CHECKING:
    from pathlib import Path

#: the SDK's server speaks the protocol under its new name; the old one is offered too
SUBPROTOCOLS = ["foxglove.sdk.v1", "foxglove.websocket.v1"]
IMU = "/view/wrist/imu"
TF = "/tf/wrist/orientation"
DAY_S = 86_400


def open_ws(url: str) -> ClientConnection:
    """A WebSocket to the server, offering the protocol's subprotocols (use it in a ``with``)."""
    return connect(url, subprotocols=SUBPROTOCOLS, open_timeout=DEADLINE_S)  # type: ignore[arg-type]


def message_class(schema_name: str, schema_b64: str) -> Any:
    """The message class of an advertised protobuf schema, from its ``FileDescriptorSet`` alone."""
    fds = descriptor_pb2.FileDescriptorSet.FromString(base64.b64decode(schema_b64))
    pool = descriptor_pool.DescriptorPool()
    for f in fds.file:   # dependencies first
        pool.Add(f)
    return message_factory.GetMessageClass(pool.FindMessageTypeByName(schema_name))


def stamp_ns(ts: Any) -> int:
    return int(ts.seconds) * 1_000_000_000 + int(ts.nanos)


class Client:
    """A Foxglove WebSocket client: the channels advertised (by topic), what it subscribed to, and every
    message received per topic as ``(log time ns, payload)``."""

    def __init__(self, ws: ClientConnection) -> None:
        self.ws = ws
        self.server_info: dict[str, Any] | None = None
        self.channels: dict[str, dict[str, Any]] = {}
        self.subs: dict[int, str] = {}
        self.msgs: dict[str, list[tuple[int, bytes]]] = {}

    def _handle(self, m: str | bytes) -> None:
        if isinstance(m, str):
            d = json.loads(m)
            if d["op"] == "serverInfo":
                self.server_info = d
            elif d["op"] == "advertise":
                for c in d["channels"]:
                    self.channels[c["topic"]] = c
            return
        op, sid, log_time = struct.unpack_from("<BIQ", m)
        assert op == 0x01, op
        self.msgs.setdefault(self.subs[sid], []).append((log_time, bytes(m[13:])))

    def pump(self, cond: Any, what: str) -> None:
        """Handle messages until ``cond()`` holds (failing after the deadline)."""
        end = time.monotonic() + DEADLINE_S
        while not cond():
            if time.monotonic() > end:
                raise AssertionError(f"timed out waiting for {what}")
            try:
                self._handle(self.ws.recv(timeout=0.05))
            except TimeoutError:
                continue

    def subscribe(self, *topics: str) -> None:
        subs = []
        for topic in topics:
            sid = len(self.subs) + 1
            self.subs[sid] = topic
            subs.append({"id": sid, "channelId": self.channels[topic]["id"]})
        self.ws.send(json.dumps({"op": "subscribe", "subscriptions": subs}))

    def decoded(self, topic: str) -> list[tuple[int, Any]]:
        c = self.channels[topic]
        cls = message_class(c["schemaName"], c["schema"])
        return [(t, cls.FromString(p)) for t, p in self.msgs.get(topic, [])]

    def wait_closed(self) -> None:
        """Read until the server closes the connection."""
        end = time.monotonic() + DEADLINE_S
        while True:
            assert time.monotonic() < end, "the server did not close the connection"
            try:
                self._handle(self.ws.recv(timeout=0.2))
            except TimeoutError:
                continue
            except ConnectionClosed:
                return


def check_log_times(msgs: list[tuple[int, bytes]], start_wall_s: float) -> None:
    """Wall-clock log times (within a day of the take's start), never going back."""
    times = [t for t, _ in msgs]
    assert all(abs(t / 1e9 - start_wall_s) < DAY_S for t in times), (times[0], start_wall_s)
    assert all(b >= a for a, b in itertools.pairwise(times))


def session_channels(path: Path) -> dict[str, tuple[str, str, bytes, dict[str, str]]]:
    """Per topic: (message encoding, schema name, schema data, channel metadata) of a session file."""
    with open(path, "rb") as f:
        summary = make_reader(f).get_summary()
    assert summary is not None
    out = {}
    for ch in summary.channels.values():
        sc = summary.schemas[ch.schema_id]
        out[ch.topic] = (ch.message_encoding, sc.name, sc.data, dict(ch.metadata))
    return out


def session_messages(path: Path, topic: str) -> list[bytes]:
    with open(path, "rb") as f:
        return [m.data for _, _, m in make_reader(f).iter_messages(topics=[topic])]


def test_live_capture_is_the_session_s_view_messages(tmp_path: Path) -> None:
    """A capture recorded and served live at once: the advertised schemas are the session's, each /view
    and /tf message received equals the session's sample at its bus time (with log time = its timestamp,
    the bus time on the wall clock, never going back), events reach /log, and the server stops with the
    capture."""
    out = tmp_path / "take.mcap"
    cap = Capture(["wrist=synth://imu?rate=200&seed=1"], output=str(out), fsync=False)
    try:
        cap.enable_orientation("fusion")
        pub = start(cap, port=0)
    except BaseException:
        cap.stop()
        raise
    assert pub.url.startswith("ws://127.0.0.1:")
    try:
        with open_ws(pub.url) as ws:
            c = Client(ws)
            c.pump(lambda: LOG_TOPIC in c.channels, "the /log channel")
            assert c.server_info is not None and c.server_info["name"] == "perfcap"
            c.subscribe(LOG_TOPIC)
            cap.start()
            c.pump(lambda: IMU in c.channels and TF in c.channels, "the stream channels")
            c.subscribe(IMU, TF)
            c.pump(lambda: len(c.msgs.get(IMU, [])) >= 100 and len(c.msgs.get(TF, [])) >= 50, "messages")
            cap.bus.publish(DeviceEvent("wrist", EventKind.NOTE, cap.clock.now_ns(), "marker for foxglove"))
            c.pump(lambda: any("marker for foxglove" in m.message for _, m in c.decoded(LOG_TOPIC)), "the event")
            report = cap.stop()
            c.wait_closed()
    finally:
        cap.stop()
    assert pub.server.stopped
    with pytest.raises(OSError), open_ws(pub.url):
        pass

    fox = [s for s in report.subscribers if s["name"] == "foxglove"]
    assert len(fox) == 1 and fox[0]["policy"] == Overflow.KEEP_NEWEST.value and fox[0]["delivered"] > 0
    assert "dropped" in fox[0]

    # the advertised channels are the session's: same encoding, schema name, schema data and metadata
    rec = session_channels(out)
    assert {IMU, TF, LOG_TOPIC} <= set(c.channels)
    for topic, ch in c.channels.items():
        enc, name, data, meta = rec[topic]
        assert (ch["encoding"], ch["schemaName"], base64.b64decode(ch["schema"])) == (enc, name, data), topic
        assert ch.get("schemaEncoding", "protobuf") == "protobuf"
        assert ch.get("metadata", {}) == meta, topic

    reader = SessionReader.open(str(out))
    start_wall = float(reader.meta["start_wall_time_s"])
    imu = reader.samples("wrist/imu")
    rows = dict(zip(imu.t_bus_ns.tolist(), imu.values.tolist(), strict=True))
    last = 0
    received = c.decoded(IMU)
    for log_time, m in received:
        ts = stamp_ns(m.timestamp)
        assert log_time == max(ts, last)
        last = log_time
        fields = [f.name for f in m.DESCRIPTOR.fields][1:]
        assert [getattr(m, f) for f in fields] == rows[ts - pub.offset_ns]
    assert fields == list(reader.streams["wrist/imu"].channels)

    # /tf: the session's FrameTransform at the same bus time, its frame at the same place in the 3D view
    offset = reader.meta.get("log_time_offset_ns")
    assert offset is not None
    cls = message_class(c.channels[TF]["schemaName"], c.channels[TF]["schema"])
    recorded = {stamp_ns(m.timestamp) - int(offset): m for m in map(cls.FromString, session_messages(out, TF))}
    for _, m in c.decoded(TF):
        r = recorded[stamp_ns(m.timestamp) - pub.offset_ns]
        assert (m.parent_frame_id, m.child_frame_id) == (r.parent_frame_id, r.child_frame_id) == ("world",
                                                                                                   "wrist/orientation")
        assert (m.translation.x, m.rotation.w, m.rotation.x, m.rotation.y, m.rotation.z) == (
            r.translation.x, r.rotation.w, r.rotation.x, r.rotation.y, r.rotation.z)
    for topic in (IMU, TF, LOG_TOPIC):
        check_log_times(c.msgs[topic], start_wall)
    assert pub.sent[IMU] >= len(received)


def test_single_samples_and_streams_seen_late_on_a_bare_bus() -> None:
    """Single samples become one-row batches; a stream first seen in the data gets its channels then, from
    the lookup (or with generic channel names); an orientation kind also goes out as /tf."""
    dev = DeviceIdentity("test", "t1")
    declared = StreamInfo("t1/x", "imu", ("a", "b"), ("m/s^2", "rad/s"), 100.0, dev)
    late = StreamInfo("t1/late", "quat", ("w", "x", "y", "z"), ("1",) * 4, None, dev)
    lookups: list[str] = []

    def lookup(name: str) -> StreamInfo | None:
        lookups.append(name)
        return late if name == late.name else None

    bus = SampleBus()
    pub = FoxglovePublisher(FoxgloveServer(port=0), bus.clock, [declared], lookup=lookup)
    sub = bus.subscribe(pub, policy=Overflow.KEEP_NEWEST, name="foxglove")
    topics = ["/view/t1/x", "/view/t1/late", "/tf/t1/late", "/view/t1/anon"]
    sent: dict[str, dict[int, tuple[float, ...]]] = {"t1/x": {}, "t1/late": {}, "t1/anon": {}}
    t = 10_000_000_000
    k = 0

    def publish_round() -> None:
        nonlocal t, k
        t += 1_000_000
        k += 1
        for stream, values in (("t1/x", (float(k), -0.5 * k)), ("t1/late", (1.0, 0.0, 0.0, 0.0)),
                               ("t1/anon", (k * 0.25,))):
            sent[stream][t] = values
            bus.publish(Sample(stream, k, t, None, t, values))

    try:
        with open_ws(pub.url) as ws:
            c = Client(ws)
            publish_round()
            c.pump(lambda: all(tp in c.channels for tp in topics), "the channels of every stream")
            c.subscribe(*topics)

            def enough() -> bool:
                publish_round()
                return all(len(c.msgs.get(tp, [])) >= 5 for tp in topics)

            c.pump(enough, "messages on every channel")
    finally:
        bus.close()
    assert sub.stats().errors == 0
    assert lookups == ["t1/late", "t1/anon"]
    assert c.channels["/view/t1/anon"]["schemaName"] == "perfcap.view.t1_anon"
    generic = StreamInfo("t1/anon", "unknown", ("c0",), ("?",), None, DeviceIdentity(kind="unknown", name="t1"))
    for info in (declared, late, generic):
        topic = f"/view/{info.name}"
        assert base64.b64decode(c.channels[topic]["schema"]) == sample_view(info).schema.data, topic
        for _, m in c.decoded(topic):
            values = tuple(getattr(m, f.name) for f in m.DESCRIPTOR.fields[1:])
            assert values == sent[info.name][stamp_ns(m.timestamp) - pub.offset_ns], topic
    assert all(m.child_frame_id == "t1/late" and m.rotation.w == 1.0 for _, m in c.decoded("/tf/t1/late"))
    assert pub.server.stopped


def test_a_busy_port_is_a_one_line_config_error() -> None:
    first = FoxgloveServer(port=0)
    try:
        with pytest.raises(ConfigError, match=r"cannot listen for the Foxglove server on 127\.0\.0\.1:\d+: .*in use"
                           ) as e:
            FoxgloveServer(port=first.port)
        assert "\n" not in str(e.value)
    finally:
        first.stop()
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        s.listen()
        with pytest.raises(ConfigError, match="in use"):
            FoxgloveServer(port=s.getsockname()[1])
    with pytest.raises(ConfigError, match=r"Foxglove server on 192\.0\.2\.1"):
        FoxgloveServer("192.0.2.1", 0)   # not an address of this machine


def test_urls_and_the_serve_flag() -> None:
    assert ws_url("0.0.0.0", 8765) == "ws://127.0.0.1:8765"
    assert ws_url("::1", 9) == "ws://[::1]:9"
    parser = build_parser()
    assert flag_values(parser.parse_args(["serve", "--foxglove"]), ServeConfig)["foxglove"] == FOXGLOVE_PORT
    assert flag_values(parser.parse_args(["serve", "--foxglove=0"]), ServeConfig)["foxglove"] == 0
    assert "foxglove" not in flag_values(parser.parse_args(["serve"]), ServeConfig)
    assert ServeConfig().foxglove == -1
    with pytest.raises(ConfigError, match="--foxglove"):
        flag_values(parser.parse_args(["serve", "--foxglove=70000"]), ServeConfig)


def _record(tmp_path: Path, *extra: str) -> subprocess.CompletedProcess[str]:
    return subprocess.run([sys.executable, "-m", "capture.app.cli", "record", "-d", "synth://imu?rate=100&seed=3",
                           "--duration", "1", "-q", "-o", str(tmp_path / "t.mcap"), *extra],
                          check=False, capture_output=True, text=True, timeout=DEADLINE_S * 3)


def test_record_with_foxglove_prints_the_url_and_records(tmp_path: Path) -> None:
    p = _record(tmp_path, "--foxglove=0")
    assert p.returncode == 0, p.stderr
    assert re.search(r"Foxglove: open ws://127\.0\.0\.1:\d+ in the Foxglove app", p.stderr), p.stderr
    assert (tmp_path / "t.mcap").is_file()


def test_record_on_a_busy_port_says_so_in_one_line_and_makes_no_file(tmp_path: Path) -> None:
    busy = FoxgloveServer(port=0)
    try:
        p = _record(tmp_path, f"--foxglove={busy.port}")
    finally:
        busy.stop()
    assert p.returncode == 2, p.stderr
    assert "Traceback" not in p.stderr
    lines = [ln for ln in p.stderr.splitlines() if ln.startswith("perfcap: error:")]
    assert len(lines) == 1 and "cannot listen for the Foxglove server" in lines[0], p.stderr
    assert not (tmp_path / "t.mcap").exists()
