"""No message can end a device (issue 16).

Regression tests for what the attempts found (a phone page ``"sent": -1e308`` or a pong
``"t": 1e305`` raised ``OverflowError`` out of the device, which then FAILED and dropped all later
data; text lines and HyperIMU took ``inf`` and ``1e999``; one Sensor Logger message with a huge
``messageId`` made every later one "late"), the device layer's net (an exception in a device's
decode path is that chunk's counted error), and the class: every device kind fuzzed with
structure-aware mutations through the real device object and a real reader
(``device_fuzz_helpers``; a seeded loop, bounded in count). The larger campaign is
``benchmarks/fuzz_devices.py``.
"""

from __future__ import annotations

import json
import logging
import math
from typing import TYPE_CHECKING, Any

import pytest
from device_fuzz_helpers import KINDS, Kind, ScriptTransport, fuzz_kind, run_reader

from capture.errors import ProtocolError
from capture.sample import Chunk, DeviceClockSpec, DeviceEvent, Direction, EventKind, Sample, StreamInfo
from devices.base import Device, Reading
from devices.codecs.hyperimu import HyperImuCodec
from devices.codecs.textline import TextLineCodec
from devices.phone import PhonePage
from devices.textline import TextLineImu
from devices.transports import open_transport
from sim_devices.phone_sim import page_hello, page_messages

if TYPE_CHECKING:
    from collections.abc import Iterable

T0 = 10**12


def samples(items: list[Any]) -> list[Sample]:
    return [x for x in items if isinstance(x, Sample)]


# -- the messages of the issue --------------------------------------------------------------------------
ISSUE_MESSAGES = [b'{"type":"data","seq":3,"sent":-1e308}', b'{"type":"pong","h":5,"t":1e305}',
                  b'{"type":"data","seq":4,"sent":1e300,"m":[[1.0,0,0,0,0,9.8,0,0,0,0,16]]}',
                  b'{"type":"hello","v":1,"id":"x","platform":"ios","t":-1e308}']


@pytest.mark.parametrize("bad", ISSUE_MESSAGES)
def test_an_out_of_range_page_number_is_refused_by_the_codec_with_its_reason(bad: bytes, caplog) -> None:
    dev = PhonePage("ph", open_transport("loop://"), {})
    with caplog.at_level(logging.WARNING):
        items = dev.process_chunk(Chunk(bad, T0, Direction.RX))
    assert not samples(items) and dev.codec.stats.framing_errors == 1 and dev.stats.decode_errors == 0
    assert "out of range" in caplog.text
    assert any(isinstance(x, DeviceEvent) and x.kind is EventKind.PROTOCOL_ERRORS for x in items)


def test_a_page_that_sends_the_issue_messages_keeps_streaming_through_a_reader() -> None:
    """Through a real DeviceReader and bus: the device ends FINISHED (not FAILED) and every sample
    of the good messages after the bad ones is delivered."""
    good = [m.data for m in page_messages(2.0)]
    data = [page_hello(), *good[:10], *ISSUE_MESSAGES, *good[10:]]
    chunks = [Chunk(d, T0 + i * 50_000_000, Direction.RX) for i, d in enumerate(data)]
    ref = PhonePage("ref", open_transport("loop://"), {})
    want = sum(len(samples(ref.process_chunk(Chunk(d, T0, Direction.RX)))) for d in [page_hello(), *good])
    kind = Kind("phone page", "phone_page", lambda tr: PhonePage("ph", tr, {}), [], lambda r, d: d)
    state, got = run_reader(kind, chunks)
    assert state == "finished" and got == want > 0


# -- the device layer's net -----------------------------------------------------------------------------
class FragileDevice(Device[TextLineCodec]):
    """A device kind whose frame mapping raises on a line starting with 0 (a bug in a kind's code),
    gives an infinite value on a line starting with 1, and ticks beyond its clock on one with 2."""

    kind = "fragile"
    codec_cls = TextLineCodec

    def declare_streams(self) -> list[StreamInfo]:
        return [self.stream_info("v", "extra", ("a", "b"), ("1", "1"), 100.0, None, DeviceClockSpec(1e6))]

    def frame_to_readings(self, frame: Any) -> Iterable[Reading]:
        a, b = frame.values
        if a == 0:
            return [Reading(0, (1 / a, b), 0)]
        if a == 1:
            return [Reading(0, (math.inf, b), 1)]
        if a == 2:
            return [Reading(0, (a, b), 2 ** 70)]
        return [Reading(0, (a, b), round(b))]


def fragile(strict: bool = False) -> FragileDevice:
    d = FragileDevice("f", open_transport("loop://"), strict=strict)
    d.codec = TextLineCodec(strict, fmt="csv", columns=("a", "b"))
    return d


def test_an_exception_in_a_devices_decode_path_is_that_chunks_counted_error(caplog) -> None:
    d = fragile()
    out: list[Any] = []
    with caplog.at_level(logging.WARNING):
        for i, line in enumerate([b"5,1000\n", b"0,2000\n", b"5,3000\n", b"0,4000\n", b"5,5000\n"]):
            out += d.process_chunk(Chunk(line, T0 + i * 10_000_000, Direction.RX))
    assert [s.values for s in samples(out)] == [(5.0, 1000.0), (5.0, 3000.0), (5.0, 5000.0)]
    h = d.health()
    assert h["decode_errors"] == 2 and h["framing_errors"] == 2 and h["state"] == "closed"
    assert "ZeroDivisionError" in caplog.text and "the device goes on" in caplog.text
    assert sum(isinstance(x, DeviceEvent) and x.kind is EventKind.PROTOCOL_ERRORS for x in out) == 2


def test_decode_errors_are_logged_with_a_rate_limit(caplog) -> None:
    d = fragile()
    with caplog.at_level(logging.WARNING, logger="devices.base"):
        for i in range(3000):
            d.process_chunk(Chunk(b"0,1\n", T0 + i, Direction.RX))
    assert d.stats.decode_errors == 3000
    assert 5 <= len([r for r in caplog.records if "could not be decoded" in r.message]) <= 10


def test_readings_the_clock_or_the_floats_cannot_carry_are_refused_and_counted() -> None:
    d = fragile()
    out: list[Any] = []
    for i, line in enumerate([b"5,1000\n", b"1,2000\n", b"2,3000\n", b"5,4000\n"]):
        out += d.process_chunk(Chunk(line, T0 + i * 10_000_000, Direction.RX))
    assert [s.values for s in samples(out)] == [(5.0, 1000.0), (5.0, 4000.0)]
    assert d.stats.bad_readings == 2 and d.stats.decode_errors == 0 and d.codec.stats.framing_errors == 2


def test_strict_mode_raises_a_decode_error_as_a_protocol_error() -> None:
    d = fragile(strict=True)
    with pytest.raises(ProtocolError, match="ZeroDivisionError"):
        d.process_chunk(Chunk(b"0,1\n", T0, Direction.RX))


def test_a_reader_keeps_a_fragile_device_streaming() -> None:
    lines = [b"0,1\n" if i % 3 == 0 else f"5,{i * 10_000}\n".encode() for i in range(300)]
    chunks = [Chunk(x, T0 + i * 10_000_000, Direction.RX) for i, x in enumerate(lines)]
    dev = FragileDevice("f", ScriptTransport(chunks))
    dev.codec = TextLineCodec(fmt="csv", columns=("a", "b"))
    kind = Kind("fragile", "textline", lambda tr: dev, [], lambda r, d: d)
    state, got = run_reader(kind, chunks)
    assert state == "finished" and got == 200 and dev.stats.decode_errors == 100


# -- codecs refuse what no sensor reads ---------------------------------------------------------------------
@pytest.mark.parametrize("field", [b"inf", b"-inf", b"Infinity", b"1e999", b"-1e999"])
def test_text_lines_refuse_infinite_numbers(field: bytes) -> None:
    for fmt, line in (("csv", b"1," + field + b",3\n"), ("kv", b"t:1 ax:" + field + b" ay:3\n")):
        c = TextLineCodec(fmt=fmt, columns=("t", "ax", "ay"))
        assert c.feed(line + b"1,2,3\n" if fmt == "csv" else line + b"t:1 ax:2 ay:3\n") != []
        assert c.stats.framing_errors == 1 and c.stats.frames == 1


def test_text_lines_keep_nan_as_no_value() -> None:
    (f,) = TextLineCodec(fmt="csv", columns=("t", "ax")).feed(b"1,nan\n")
    assert math.isnan(f.values[1])


def test_hyperimu_refuses_infinite_numbers() -> None:
    c = HyperImuCodec(sensors=("accelerometer",))
    assert len(c.feed(b"1e999,0.5,0.25\r\n0.1,inf,0.25\r\n0.1,0.5,0.25\r\n")) == 1
    assert c.stats.framing_errors == 2


def test_a_unit_that_scales_a_value_to_infinity_is_refused() -> None:
    d = TextLineImu("s", open_transport("loop://"), {"format": "csv", "columns": "t,mx,my,mz",
                                                     "units": "ms,gauss,gauss,gauss", "time": "t"})
    out = d.process_chunk(Chunk(b"1,1e307,0,0\n2,1,0,0\n", T0, Direction.RX))
    assert [s.values for s in samples(out)] == [(100.0, 0.0, 0.0)] and d.stats.bad_readings == 1


def test_a_sensor_logger_message_far_ahead_does_not_make_later_ones_late() -> None:
    kind = KINDS["sensorlogger"]()
    assert kind.renumber is not None
    d = kind.make()
    msgs = [kind.renumber(m, i) for i, m in enumerate(kind.good[:6])]
    msgs[2] = kind.renumber(kind.good[2], 2 ** 53 - 1)
    got = [len(samples(d.process_chunk(Chunk(m, T0 + i * 500_000_000, Direction.RX)))) for i, m in enumerate(msgs)]
    assert got[2] == 0 and all(got[i] > 0 for i in (0, 1, 3, 4, 5))
    assert d.health()["id_jumps"] == 1 and d.health()["late_messages"] == 0
    # a real jump, confirmed by the next message, starts the new numbering
    more = [kind.renumber(kind.good[k], 10 ** 9 + k) for k in (6, 7, 8)]
    got = [len(samples(d.process_chunk(Chunk(m, T0 + (10 + i) * 500_000_000, Direction.RX))))
           for i, m in enumerate(more)]
    assert got[0] == 0 and got[1] > 0 and got[2] > 0 and d.health()["id_jumps"] == 2


# -- the class: every device kind, fuzzed --------------------------------------------------------------------
#: mutated messages per device kind in CI (about a second each); benchmarks/fuzz_devices.py runs more
CI_INPUTS = 400


@pytest.mark.parametrize("key", sorted(KINDS))
def test_no_mutated_message_ends_a_device_or_is_lost_silently(key: str, caplog) -> None:
    caplog.set_level(logging.ERROR)
    res = fuzz_kind(key, CI_INPUTS, seed=16)
    assert res.inputs == CI_INPUTS
    assert not res.problems(), f"{res.kind}: {res.problems()}; {res.examples}"


@pytest.mark.parametrize("key", ["phone", "sensorserver"])
def test_an_integer_beyond_a_floats_range_is_refused_by_the_json_codecs(key: str) -> None:
    kind = KINDS[key]()
    d = kind.make()
    good = kind.good[1] if key == "phone" else kind.good[0]
    obj = json.loads(good)
    if key == "phone":
        obj["m"][0][4] = 10 ** 400
    else:
        obj["values"][0] = 10 ** 400
    d.process_chunk(Chunk(json.dumps(obj).encode(), T0, Direction.RX))
    assert d.codec.stats.framing_errors == 1 and d.stats.decode_errors == 0


def test_an_empty_nintendo_report_is_counted() -> None:
    d = KINDS["nintendo"]().make()
    before = d.codec.stats.framing_errors
    d.process_chunk(Chunk(b"", T0, Direction.RX))
    assert d.codec.stats.framing_errors == before + 1
