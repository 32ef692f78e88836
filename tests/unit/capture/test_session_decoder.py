"""The ``mcap`` library's decoded reader with perfcap's decoders (``capture.session_decoder``): every message of
a session decodes, to the same samples, raw chunks, clock fits and events that ``SessionReader`` reads, from
takes of serial, HID and evemu devices, and from a format 1 session (written before the viewable channels,
``tests/data/format1_session.mcap``); the viewable channels decode to the samples and events they show; other
encodings are left to other factories; a damaged block is a ``ValueError`` from the decoder."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
from mcap.decoder import DecoderFactory as McapDecoderFactory
from mcap.exceptions import DecoderNotFoundError
from mcap.reader import make_reader
from mcap.records import Schema

from capture.app.orchestrator import Capture
from capture.session import LOG_TIME_OFFSET_KEY, SessionReader
from capture.session_blocks import PROTOBUF, RAW_BLOCK, SAMPLE_BLOCK
from capture.session_decoder import DecoderFactory

TRACES = Path(__file__).resolve().parents[3].parent / "shared" / "traces"
MOUSE = TRACES / "f_pen_mouse_touch" / "evemu" / "saitek_cyborg_rat5_mouse.events"
ROLLER = TRACES / "b_hid" / "hid_recorder" / "contour_rollermouse_red_doubleclick.hid"
FORMAT1 = Path(__file__).resolve().parents[2] / "data" / "format1_session.mcap"


@pytest.fixture(scope="module")
def new_session(tmp_path_factory: pytest.TempPathFactory) -> Path:
    missing = [str(p) for p in (MOUSE, ROLLER) if not p.exists()]
    if missing:
        pytest.skip(f"{', '.join(missing)} not found (../shared/traces must sit beside the project)")
    urls = ["w=witmotion@synth://imu?realtime=false&duration=2&rate=100&device_clock=true",
            "a=synth://imu?rate=100&seed=1&realtime=false&duration=2",
            f"m=hid@simhid://mouse?evemu={MOUSE}&realtime=false&latency_ms=0",
            f"r=hid@simhid://{ROLLER}?realtime=false&latency_ms=0"]
    out = tmp_path_factory.mktemp("dec") / "take.mcap"
    rep = Capture(urls, output=str(out), fsync=False).run(None)
    assert rep.recorder_error is None
    return out


@pytest.fixture(scope="module", params=["format 2", "format 1"])
def session(request: pytest.FixtureRequest, new_session: Path) -> Path:
    return new_session if request.param == "format 2" else FORMAT1


def test_every_message_decodes_to_what_the_session_reader_reads(session: Path) -> None:
    r = SessionReader(str(session))
    samples: dict[str, list] = {}
    raw: dict[str, list] = {}
    clock: dict[str, list] = {}
    events = []
    views: dict[str, list] = {}
    with session.open("rb") as f:
        for _, channel, _, decoded in make_reader(f, decoder_factories=[DecoderFactory()]).iter_decoded_messages(
                log_time_order=False):
            topic = channel.topic
            if topic.startswith("/samples/"):
                samples.setdefault(topic.removeprefix("/samples/"), []).append(decoded)
            elif topic.startswith("/raw/"):
                raw.setdefault(topic.removeprefix("/raw/"), []).extend(decoded)
            elif topic.startswith("/clock/"):
                clock.setdefault(topic.removeprefix("/clock/"), []).append(decoded)
            elif topic.startswith(("/view/", "/tf/", "/log")):
                views.setdefault(topic, []).append(decoded)
            else:
                assert topic == "/events"
                events.append(decoded)
    assert bool(views) == (r.meta["format_version"] != "1")
    assert set(samples) == {s for s in r.streams if len(r.samples(s))} and len(samples) >= 4
    for stream, blocks in samples.items():
        want = r.samples(stream)
        got_vals = np.concatenate([b.values for b in blocks])
        got_bus = np.concatenate([b.t_bus_ns for b in blocks])
        assert len(want) > 0
        np.testing.assert_array_equal(got_vals, want.values)
        np.testing.assert_array_equal(got_bus, want.t_bus_ns)
        np.testing.assert_array_equal(np.concatenate([b.t_host_ns for b in blocks]), want.t_host_ns)
    for device in r.devices:
        assert [c.data for c in raw.get(device, [])] == [c.data for c in r.raw_chunks(device)]
        assert sum(len(c.data) for c in raw.get(device, [])) > 0, device
    assert events == r.events() and events
    for stream, fits in clock.items():
        assert fits == r.clock_states(stream)
    if views:
        offset = int(r.meta[LOG_TIME_OFFSET_KEY])
        for stream in samples:
            want = r.samples(stream)
            got = views[f"/view/{stream}"]
            assert len(got) == len(want)
            fields = [f.name for f in got[0].DESCRIPTOR.fields][1:]
            np.testing.assert_array_equal([[getattr(m, k) for k in fields] for m in got], want.values)
            np.testing.assert_array_equal([m.timestamp.seconds * 10**9 + m.timestamp.nanos for m in got],
                                          want.t_bus_ns + offset)
        assert [m.message.split(":")[0] for m in views["/log"]] == [e["kind"] for e in events]


def test_the_blocks_are_protobuf_with_their_schemas(new_session: Path) -> None:
    with new_session.open("rb") as f:
        for schema, channel, _ in make_reader(f).iter_messages():
            if channel.topic.startswith(("/raw/", "/samples/")):
                assert channel.message_encoding == PROTOBUF and schema is not None
                assert schema.name == (RAW_BLOCK if channel.topic.startswith("/raw/") else SAMPLE_BLOCK).name


def test_without_the_factory_the_library_cannot_decode_format_1() -> None:
    # what a viewer without perfcap's code met before format 2 (issue 18's starting point)
    with FORMAT1.open("rb") as f, pytest.raises(DecoderNotFoundError):
        for _ in make_reader(f).iter_decoded_messages():
            pass


def test_other_encodings_are_left_to_other_factories() -> None:
    fac = DecoderFactory()
    assert isinstance(fac, McapDecoderFactory)
    js = Schema(id=2, name="x", encoding="jsonschema", data=json.dumps({"type": "object"}).encode())
    assert fac.decoder_for("json", js) is not None   # json with a JSON Schema: the object
    assert fac.decoder_for("json", None) is not None
    assert fac.decoder_for("cdr", None) is None
    assert fac.decoder_for("ros1", Schema(id=3, name="std_msgs/String", encoding="ros1msg", data=b"")) is None


@pytest.mark.parametrize("topic", ["/samples/", "/raw/"])
def test_a_damaged_block_is_a_value_error(session: Path, topic: str) -> None:
    with session.open("rb") as f:
        found = [(s, c, m.data) for s, c, m in make_reader(f).iter_messages() if c.topic.startswith(topic)]
    schema, channel, _ = found[0]
    blocks = [d for _, _, d in found]
    dec = DecoderFactory().decoder_for(channel.message_encoding, schema)
    assert dec is not None
    rng = np.random.default_rng(3)
    refused = 0
    for _ in range(400):   # truncated, or with a corrupt byte in its header: a clear error, never another
        data = blocks[int(rng.integers(0, len(blocks)))]
        cut = bytearray(data[: int(rng.integers(0, len(data)))])
        if cut and rng.random() < 0.5:
            cut[int(rng.integers(0, min(16, len(cut))))] ^= int(rng.integers(1, 256))
        try:
            dec(bytes(cut))
        except ValueError:
            refused += 1
    assert refused > 300
