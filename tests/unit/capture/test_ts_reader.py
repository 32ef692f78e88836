"""The official TypeScript MCAP reader (``@mcap/core`` from npm, run by ``tests/js/read_session.mjs``) reads
perfcap sessions (issue 18): every message of every channel, through the index, with the same schemas,
channels, message counts and log times as the Python ``mcap`` reader; log times monotonic per channel and
no publish time after its log time; a session cut short, as a killed recorder leaves it, is read by the
stream reader up to the cut. The MCAP files among ``../shared/traces`` are compared the same way.

Needs node and npm, and the npm registry the first time (``js_reader_helpers`` installs the pinned packages);
without them the tests skip and say so.
"""

from __future__ import annotations

import shutil
from collections import Counter
from pathlib import Path
from typing import Any

import js_reader_helpers
import pytest
from mcap.reader import make_reader
from mcap.records import Attachment, Channel, Header, Message, Metadata, Schema
from mcap.stream_reader import StreamReader

from capture.app.orchestrator import Capture

TRACES = Path(__file__).resolve().parents[3].parent / "shared" / "traces"
# simulated devices of three transports (serial IMU, DualSense and a pen tablet over HID), at their real rates
DEVICES = ["imu=synth://imu?rate=200&seed=1", "pad=dualsense@simhid://dualsense?seed=5", "pen=hid@simhid://pen?seed=6"]
RECORD_S = 1.5
CUT_FRACTION = 0.6


class _Tally:
    """Per-channel message figures in the order the messages are given (the file's order here)."""

    def __init__(self) -> None:
        self.by_channel: dict[int, dict[str, Any]] = {}

    def add(self, m: Message) -> None:
        t = self.by_channel.get(m.channel_id)
        if t is None:
            t = self.by_channel[m.channel_id] = {
                "count": 0, "dataBytes": 0, "first": m.log_time, "last": m.log_time, "min": m.log_time,
                "max": m.log_time, "monotonic": True, "publishAfterLog": False}
        t["monotonic"] = t["monotonic"] and m.log_time >= t["last"]
        t["publishAfterLog"] = t["publishAfterLog"] or m.publish_time > m.log_time
        t["min"], t["max"] = min(t["min"], m.log_time), max(t["max"], m.log_time)
        t["count"] += 1
        t["dataBytes"] += len(m.data)
        t["last"] = m.log_time


def _schema(s: Schema) -> dict[str, Any]:
    return {"id": s.id, "name": s.name, "encoding": s.encoding, "dataLength": len(s.data)}


def _channel(c: Channel) -> dict[str, Any]:
    return {"id": c.id, "topic": c.topic, "messageEncoding": c.message_encoding, "schemaId": c.schema_id,
            "metadataKeys": sorted(c.metadata)}


def python_indexed(path: Path) -> dict[str, Any]:
    """What the Python reader reads through the file's summary, every message in file order."""
    with path.open("rb") as f:
        reader = make_reader(f, validate_crcs=True)
        header = reader.get_header()
        summary = reader.get_summary()
        assert summary is not None, f"{path}: the Python reader finds no summary"
        tally = _Tally()
        for _, _, message in reader.iter_messages(log_time_order=False):
            tally.add(message)
        return {
            "profile": header.profile, "library": header.library,
            "schemas": [_schema(s) for _, s in sorted(summary.schemas.items())],
            "channels": [_channel(c) for _, c in sorted(summary.channels.items())],
            "statistics": summary.statistics,
            "messages": tally.by_channel,
            "metadata": [m.name for m in reader.iter_metadata()],
            "attachments": [a.name for a in reader.iter_attachments()],
        }


def python_stream(path: Path) -> dict[str, Any]:
    """What the Python stream reader reads from the start of the file up to the first error, and that error."""
    out: dict[str, Any] = {"profile": None, "library": None, "error": None, "metadata": [], "attachments": []}
    schemas: dict[int, Schema] = {}
    channels: dict[int, Channel] = {}
    tally = _Tally()
    with path.open("rb") as f:
        try:
            for r in StreamReader(f, validate_crcs=True).records:
                if isinstance(r, Header):
                    out["profile"], out["library"] = r.profile, r.library
                elif isinstance(r, Schema):
                    schemas[r.id] = r
                elif isinstance(r, Channel):
                    channels[r.id] = r
                elif isinstance(r, Message):
                    tally.add(r)
                elif isinstance(r, Metadata):
                    out["metadata"].append(r.name)
                elif isinstance(r, Attachment):
                    out["attachments"].append(r.name)
        except Exception as e:  # any error ends the reading: which one is reported
            out["error"] = f"{type(e).__name__}: {e}"
    out["schemas"] = [_schema(s) for _, s in sorted(schemas.items())]
    out["channels"] = [_channel(c) for _, c in sorted(channels.items())]
    out["messages"] = tally.by_channel
    return out


def assert_same_reading(ts: dict[str, Any], py: dict[str, Any], what: str) -> None:
    """The TypeScript reader's report and the Python reader's figures agree: header, schemas, channels, and per
    channel the message count, payload bytes, earliest and latest log times and their order in the file."""
    assert (ts["profile"], ts["library"]) == (py["profile"], py["library"]), what
    assert ts["schemas"] == py["schemas"], what
    assert ts["channels"] == py["channels"], what
    ts_msgs = ts["messages"]
    py_msgs = {str(k): v for k, v in py["messages"].items()}
    assert sorted(ts_msgs) == sorted(py_msgs), f"{what}: channels with messages differ"
    for cid, p in py_msgs.items():
        t = ts_msgs[cid]
        topic = next((c["topic"] for c in py["channels"] if str(c["id"]) == cid), cid)
        assert (t["count"], t["dataBytes"]) == (p["count"], p["dataBytes"]), f"{what}: {topic}"
        assert (int(t["minLogTime"]), int(t["maxLogTime"])) == (p["min"], p["max"]), f"{what}: {topic}"
        assert t["publishAfterLog"] == p["publishAfterLog"], f"{what}: {topic}"
        # read in file order by the TypeScript stream reader as well
        f = ts["fileOrder"]["messages"][cid]
        assert (f["count"], f["dataBytes"]) == (p["count"], p["dataBytes"]), f"{what}: {topic} in file order"
        assert f["logTimeMonotonic"] == p["monotonic"], f"{what}: {topic} in file order"
    assert ts["messageCount"] == sum(p["count"] for p in py_msgs.values()), what
    assert Counter(ts["metadata"]) == Counter(py["metadata"]), what
    assert Counter(ts["attachments"]) == Counter(py["attachments"]), what


def assert_indexed_reading(ts: dict[str, Any], py: dict[str, Any], what: str) -> None:
    """As ``assert_same_reading``, for an intact file the TypeScript reader read through its index, and every
    message the summary's statistics count was read."""
    assert ts["reader"] == "indexed", f"{what}: the indexed reader could not open it: {ts['indexError']}"
    assert ts["indexError"] is None, what
    assert (ts["error"], ts["complete"]) == (None, True), what
    assert (ts["fileOrder"]["error"], ts["fileOrder"]["complete"]) == (None, True), what
    assert_same_reading(ts, py, what)
    stats = py["statistics"]
    if stats is not None:
        assert ts["statistics"] is not None, what
        assert int(ts["statistics"]["messageCount"]) == stats.message_count == ts["messageCount"], what
        assert {int(k): int(v) for k, v in ts["statistics"]["channelMessageCounts"].items()} == {
            k: v for k, v in stats.channel_message_counts.items() if v}, what


@pytest.fixture(scope="module")
def session(tmp_path_factory: pytest.TempPathFactory) -> Path:
    js_reader_helpers.ensure_installed()  # skips before recording when node, npm or the registry is missing
    out = tmp_path_factory.mktemp("ts") / "take.mcap"
    # flushes (and closes an MCAP chunk) every 0.25 s: several chunks, so a cut leaves whole ones before it
    rep = Capture(DEVICES, output=str(out), fsync=False, max_loss_s=0.5).run(RECORD_S)
    assert rep.recorder_error is None
    return out


@pytest.fixture(scope="module")
def session_read(session: Path) -> dict[str, Any]:
    return js_reader_helpers.read_session(session)


def test_ts_reader_reads_every_message_as_the_python_reader_does(session: Path,
                                                                  session_read: dict[str, Any]) -> None:
    ts = session_read
    py = python_indexed(session)
    assert_indexed_reading(ts, py, str(session))
    assert ts["profile"] == "perfcap"
    assert ts["chunkCount"] > 1
    topics = {c["topic"] for c in ts["channels"]}
    assert {"/events", "/raw/imu", "/raw/pad", "/raw/pen", "/samples/imu/imu", "/samples/pen/pen"} <= topics
    # every device's raw chunks and samples were read, not just their channels
    for topic in ("/raw/imu", "/raw/pad", "/raw/pen", "/samples/imu/imu", "/samples/pad/imu", "/samples/pen/pen"):
        cid = next(str(c["id"]) for c in ts["channels"] if c["topic"] == topic)
        assert ts["messages"][cid]["count"] > 0, topic
    assert "perfcap.session" in ts["metadata"]
    assert "perfcap.summary" in ts["metadata"]
    assert any(a.startswith("pad/") for a in ts["attachments"])


def test_ts_reader_log_times_monotonic_and_never_before_publish_time(session_read: dict[str, Any]) -> None:
    ts = session_read
    assert ts["logTimesMonotonic"] is True
    assert ts["publishAfterLog"] is False
    assert ts["messages"]
    for cid, t in ts["messages"].items():
        assert t["logTimeMonotonic"], cid  # in the reader's log-time order
        assert ts["fileOrder"]["messages"][cid]["logTimeMonotonic"], cid  # in the order they were written
        assert not t["publishAfterLog"], cid
        # monotonic in the file: the indexed reader's first and last are the file's first and last
        assert (t["firstLogTime"], t["lastLogTime"]) == (t["minLogTime"], t["maxLogTime"]), cid
        assert int(t["firstPublishTime"]) <= int(t["firstLogTime"]), cid
        assert int(t["lastPublishTime"]) <= int(t["lastLogTime"]), cid


def test_ts_stream_reader_reads_a_cut_short_session_up_to_the_cut(session: Path, session_read: dict[str, Any],
                                                                  tmp_path: Path) -> None:
    data = session.read_bytes()
    cut = tmp_path / "killed.mcap"
    cut.write_bytes(data[: int(len(data) * CUT_FRACTION)])
    ts = js_reader_helpers.read_session(cut)
    assert ts["reader"] == "stream"
    assert ts["indexError"], "the indexed reader should not open a file without its footer"
    assert ts["complete"] is False
    assert ts["error"], "the stream reader should say where it stopped"
    assert ts["size"] == ts["bytesRead"] == cut.stat().st_size
    assert 0 < ts["messageCount"] <= session_read["messageCount"]
    assert ts["profile"] == "perfcap"
    assert "perfcap.session" in ts["metadata"]
    assert "perfcap.summary" not in ts["metadata"]
    for cid, t in ts["messages"].items():
        assert t["count"] <= session_read["messages"][cid]["count"], cid
        assert t["firstLogTime"] == session_read["messages"][cid]["firstLogTime"], cid
        assert t["logTimeMonotonic"] and not t["publishAfterLog"], cid
    # the Python stream reader reads exactly as far
    py = python_stream(cut)
    assert py["error"] is not None
    assert_same_reading(ts, py, str(cut))


def _trace_files() -> list[Path]:
    return sorted(TRACES.rglob("*.mcap")) if TRACES.is_dir() else []


@pytest.mark.parametrize("path", _trace_files() or [None], ids=lambda p: p.name if p else "none")
def test_ts_reader_reads_the_recorded_traces(path: Path | None) -> None:
    if path is None:
        where = TRACES if TRACES.is_dir() else f"{TRACES} (not found; ../shared/traces must sit beside the project)"
        pytest.skip(f"no *.mcap file under {where}")
    ts = js_reader_helpers.read_session(path)
    with path.open("rb") as f:
        indexed = ts["reader"] == "indexed" and make_reader(f).get_summary() is not None
    if indexed:
        assert_indexed_reading(ts, python_indexed(path), str(path))
    else:
        py = python_stream(path)
        assert (ts["error"] is None) == (py["error"] is None), (ts["error"], py["error"])
        assert_same_reading(ts, py, str(path))


def test_helpers_name_what_is_missing_without_node(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setattr(shutil, "which", lambda name: None)
    with pytest.raises(pytest.skip.Exception, match=r"node and npm .* not found on PATH"):
        js_reader_helpers.ensure_installed()
