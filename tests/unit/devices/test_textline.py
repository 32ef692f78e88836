"""Text-line sketches: CSV and key:value parsing, units to SI, device time with wrap, bad lines
counted (framing errors) or skipped (headers, banners), bounded buffer, lines split anywhere, the
vectorised CSV decoder equal to the per-line one, and option errors that say what is wrong."""

from __future__ import annotations

import logging
import math
import time

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from wait_helpers import DEADLINE_S

from capture.errors import ConfigError, ProtocolError
from capture.sample import Chunk, ChunkRun, Sample, SampleBatch
from devices import DEVICE_TYPES, device_class, open_device
from devices.codecs.textline import TextFrame, TextLineCodec, format_number
from devices.textline import TextLineImu, TextLineLayout
from devices.transports import open_transport
from devices.witmotion import WitMotionImu

G = 9.80665
DEG = math.pi / 180.0
EXAMPLE = {"format": "csv", "columns": "t,ax,ay,az,gx,gy,gz", "units": "ms,g,g,g,dps,dps,dps", "time": "t"}


def device(**opts) -> TextLineImu:
    return TextLineImu("s", open_transport("loop://"), opts)


def samples(items, stream: str) -> list[Sample]:
    return [x for x in items if isinstance(x, Sample) and x.stream == stream]


def codec(**kw) -> TextLineCodec:
    kw.setdefault("fmt", "auto")
    kw.setdefault("columns", ("t", "ax", "ay", "az"))
    return TextLineCodec(**kw)


# -- known lines ----------------------------------------------------------------------------------
def test_csv_example_line_in_sketch_units_becomes_si_with_device_time():
    d = device(**EXAMPLE)
    items = d.process_chunk(Chunk(b"1234,0.01,-0.02,9.81,0.1,0.2,0.3\r\n", 2_000_000_000))
    (imu,) = samples(items, "s/imu")
    assert imu.values == (0.01 * G, -0.02 * G, 9.81 * G, 0.1 * DEG, 0.2 * DEG, 0.3 * DEG)
    assert imu.values[2] == pytest.approx(96.2032365)
    assert imu.t_device_ns == 1_234_000_000
    assert d.streams[0].units == ("m/s^2",) * 3 + ("rad/s",) * 3
    assert d.streams[0].clock.tick_hz == 1e6 and d.streams[0].clock.wrap_ticks is None


def test_key_value_line_with_mixed_separators_gives_the_same_reading():
    d = device(**{**EXAMPLE, "format": "kv"})
    items = d.process_chunk(Chunk(b"t:1234 ax:0.01 ay=-0.02,az: 9.81\tgx:0.1, gy=0.2 gz:0.3 extra:7\n", 1))
    (imu,) = samples(items, "s/imu")
    assert imu.values == (0.01 * G, -0.02 * G, 9.81 * G, 0.1 * DEG, 0.2 * DEG, 0.3 * DEG)
    assert imu.t_device_ns == 1_234_000_000


def test_imu_channels_match_the_witmotion_imu_stream():
    w = WitMotionImu("w", open_transport("loop://"), {})
    assert device().streams[0].channels == w.streams[0].channels[:6] == ("ax", "ay", "az", "gx", "gy", "gz")
    assert DEVICE_TYPES["textline"] == ("devices.textline", "TextLineImu") and device_class("textline") is TextLineImu


def test_options_fit_a_url_query_and_baud_goes_to_the_transport():
    d = open_device("s=textline@serial:///dev/ttyACM0?format=csv&columns=t,ax,ay,az,gx,gy,gz"
                    "&units=us,m/s^2,m/s^2,m/s^2,rad/s,rad/s,rad/s&time=t&time_wrap=u32&baud=921600")
    assert isinstance(d, TextLineImu) and d.transport.opts["baud"] == 921600  # not opened
    assert "baud" not in d.device_options and d.device_options["time_wrap"] == "u32"
    assert d.streams[0].clock.wrap_ticks == 2 ** 32
    items = d.process_chunk(Chunk(b"4294967295,1.5,0,0,0,0,-2\n", 1))
    assert samples(items, "s/imu")[0].values == (1.5, 0.0, 0.0, 0.0, 0.0, -2.0)
    assert samples(items, "s/imu")[0].t_device_ns == 4294967295_000


def test_end_to_end_through_a_real_serial_transport():
    """pyserial's loop:// reads back what is written: a simulated sketch's line goes out, through the
    serial transport and the device, and comes back as a sample."""
    d = open_device("s=textline@loop://?" + "&".join(f"{k}={v}" for k, v in EXAMPLE.items()))
    d.open()
    try:
        d.send(TextLineLayout(EXAMPLE).encode_line({"ax": G, "gz": -DEG}, t_device_s=1.5, decimals=4))
        got: list[Sample] = []
        deadline = time.monotonic() + DEADLINE_S
        while not got and time.monotonic() < deadline:
            got += samples(d.poll(0.05), "s/imu")
    finally:
        d.close()
    assert len(got) == 1 and got[0].t_device_ns == 1_500_000_000
    assert got[0].values[0] == pytest.approx(G) and got[0].values[5] == pytest.approx(-DEG)
    assert all(math.isnan(v) for v in got[0].values[1:5])


def test_mag_and_extra_streams_and_nan_for_unmapped_channels():
    d = device(format="csv", columns="t,_,ax,ay,az,mx,my,mz,temp,Hz:loop",
               units="us,,mg,mg,mg,gauss,gauss,nT,degC,Hz", time="t", rate="50")
    assert [s.name for s in d.streams] == ["s/imu", "s/mag", "s/extra"]
    assert d.streams[2].channels == ("temp", "loop") and d.streams[2].units == ("degC", "Hz")
    assert all(s.nominal_rate_hz == 50 for s in d.streams)
    items = d.process_chunk(Chunk(b"100,IMU,1000,0,-500,0.5,-0.25,300,21.5,49.9\n", 1))
    imu, mag, ex = samples(items, "s/imu")[0], samples(items, "s/mag")[0], samples(items, "s/extra")[0]
    assert imu.values[:3] == (1000 * G * 1e-3, 0.0, -500 * G * 1e-3)
    assert all(math.isnan(v) for v in imu.values[3:])
    assert mag.values == (50.0, -25.0, 300 * 1e-3)
    assert ex.values == (21.5, 49.9)
    assert imu.t_device_ns == mag.t_device_ns == ex.t_device_ns == 100_000


def test_key_value_lines_emit_only_the_streams_they_carry():
    d = device(format="kv", columns="ax,ay,az,mx,my,mz")
    items = d.process_chunk(Chunk(b"ax:1 az:3\nmx:7 my:8 mz:9\n", 1))
    imu, mag = samples(items, "s/imu"), samples(items, "s/mag")
    assert len(imu) == 1 and len(mag) == 1
    assert imu[0].values[0] == 1.0 and math.isnan(imu[0].values[1]) and imu[0].values[2] == 3.0
    assert mag[0].values == (7.0, 8.0, 9.0)


def test_micros_counter_wrapping_at_u32_gives_continuous_device_time():
    d = device(format="csv", columns="t,ax", units="us,", time="t", time_wrap="u32", rate="100")
    start = 2 ** 32 - 45_000
    lines = [f"{(start + 10_000 * k) % 2 ** 32},{k}\n".encode() for k in range(10)]
    out = []
    for k, line in enumerate(lines):
        out += samples(d.process_chunk(Chunk(line, 1_000_000_000 + 10_000_000 * k + 500_000)), "s/imu")
    tdev = np.array([s.t_device_ns for s in out])
    assert len(out) == 10 and set(np.diff(tdev).tolist()) == {10_000_000}
    assert d.health()["clock_resets"] == 0 and d.stats.lost_readings == 0


def test_lost_lines_are_sequence_gaps_when_time_and_rate_are_known():
    d = device(format="csv", columns="t,ax", units="ms,", time="t", rate="100")
    data = b"".join(f"{t},0\n".encode() for t in (0, 10, 20, 50, 60))
    out = samples(d.process_chunk(Chunk(data, 1_000_000_000)), "s/imu")
    assert [s.seq for s in out] == [0, 1, 2, 5, 6] and d.stats.lost_readings == 2


# -- bad lines, headers, buffer bound ---------------------------------------------------------------
def test_headers_and_banners_are_skipped_bad_lines_are_framing_errors(caplog):
    c = codec(fmt="csv", time_field=0, time_max=2.0 ** 32)
    data = (b"t,ax,ay,az\r\n"           # CSV header: skipped
            b"MPU6050 ready\n"          # banner: skipped
            b"\n"                       # blank: skipped
            b"1,0.5,0.25,-1\n"          # good
            b"2,0.5,abc,-1\n"           # a mapped field is not a number
            b"3,0.5,0.25\n"             # wrong column count
            b"\xff\xfe4,1,2,3\n"        # not UTF-8
            b"-5,1,2,3\n"               # negative device time
            b"6,1,2,3,\n")              # one trailing comma is fine
    with caplog.at_level(logging.DEBUG, logger="devices.codecs"):
        out = c.feed(data)
    assert out == [TextFrame((1.0, 0.5, 0.25, -1.0), 15), TextFrame((6.0, 1.0, 2.0, 3.0), 15)]
    assert c.stats.skipped_lines == 3 and c.stats.framing_errors == 4 and c.stats.checksum_errors == 0
    text = caplog.text
    assert "field 'ay' is not a number" in text and "3 fields where 4 columns are configured" in text
    assert "not UTF-8" in text and "outside [0, 4.29497e+09)" in text and "MPU6050 ready" in text


def test_key_value_errors():
    c = codec(fmt="kv", time_field=0, time_max=1e9)
    out = c.feed(b"t:1 ax:x\nt:2 ax:1 ax:2\nax:3\nStatus: ok\nt:5 ay:2\n")
    assert len(out) == 1 and out[0].values[0] == 5.0 and out[0].values[2] == 2.0 and out[0].present == 0b0101
    assert math.isnan(out[0].values[1]) and math.isnan(out[0].values[3])
    assert c.stats.framing_errors == 3  # non-numeric value, repeated key, no time key
    assert c.stats.skipped_lines == 1   # no configured key at all


def test_strict_mode_raises_on_a_bad_line():
    with pytest.raises(ProtocolError, match="is not a number"):
        codec(fmt="csv", strict=True).feed(b"1,2,x,4\n")


def test_an_over_long_line_is_dropped_and_the_buffer_stays_bounded():
    c = codec(fmt="csv", max_line=64)
    out = []
    for _ in range(100):
        out += c.feed(b"9" * 50)
        assert c.buffered <= 65
    out += c.feed(b"1,2,3,4\n" + b"5,6,7,8\n")
    assert [f.values for f in out] == [(5.0, 6.0, 7.0, 8.0)]  # the end of the long line is not a line
    assert c.stats.framing_errors == 1 and c.stats.skipped_bytes == 5000 + 8


# -- splitting and fuzzing ---------------------------------------------------------------------------
numbers = st.one_of(st.integers(-10 ** 6, 10 ** 6).map(str),
                    st.floats(-1e6, 1e6, allow_nan=False).map(repr),
                    st.decimals(-10 ** 5, 10 ** 5, places=4, allow_nan=False, allow_infinity=False).map(str))
good_csv = st.tuples(st.integers(0, 10 ** 9), numbers, numbers, numbers).map(
    lambda r: ",".join(str(x) for x in r).encode())
good_kv = st.tuples(st.integers(0, 10 ** 9), numbers, numbers).map(lambda r: f"t:{r[0]} ax={r[1]}, az:{r[2]}".encode())
odd = st.sampled_from([b"t,ax,ay,az", b"MPU6050 ready", b"", b"1,2", b"1,x,2,3", b"\xff\xfe1,2,3,4", b"ax:1",
                       b"t:1 ax:q", b"  7 , 8 , 9 , 10  ", b"1 2 3 4", b"-1,0,0,0"])
line_lists = st.lists(st.one_of(good_csv, good_kv, odd).map(
    lambda b: b + b"\n"), min_size=1, max_size=30).map(lambda ls: [x.replace(b"\n", b"\r\n", 1) if len(x) % 3 == 0
                                                                   else x for x in ls])


@settings(max_examples=150, deadline=None)
@given(line_lists, st.lists(st.integers(1, 40), max_size=40))
def test_lines_split_at_any_boundary_decode_the_same(lines, cuts):
    data = b"".join(lines)
    ref = codec(time_field=0, time_max=2.0 ** 32)
    want = ref.feed(data)
    c = codec(time_field=0, time_max=2.0 ** 32)
    out, i = [], 0
    for n in cuts:
        out += c.feed(data[i:i + n])
        i += n
    out += c.feed(data[i:])
    assert [(f.values, f.present) for f in out] == [(f.values, f.present) for f in want] or _nan_equal(out, want)
    assert c.stats.as_dict() == ref.stats.as_dict()
    assert c.stats.frames + c.stats.framing_errors + c.stats.skipped_lines == len(lines)


@settings(max_examples=150, deadline=None)
@given(line_lists, st.sampled_from(["csv", "auto"]))
def test_the_fast_path_for_all_numeric_lines_changes_nothing(lines, fmt):
    data = b"".join(lines)
    fast = codec(fmt=fmt, time_field=0, time_max=2.0 ** 32)
    slow = codec(fmt=fmt, time_field=0, time_max=2.0 ** 32)
    assert fast._fast
    slow._fast = False
    assert _nan_equal(fast.feed(data), slow.feed(data))
    assert fast.stats.as_dict() == slow.stats.as_dict() and fast.last_format == slow.last_format


def _nan_equal(a: list[TextFrame], b: list[TextFrame]) -> bool:
    return [(np.array(f.values).tobytes(), f.present) for f in a] == [(np.array(f.values).tobytes(), f.present)
                                                                      for f in b]


@settings(max_examples=200, deadline=None)
@given(st.binary(max_size=300), st.lists(st.integers(1, 50), max_size=10), st.sampled_from(["csv", "kv", "auto"]))
def test_random_bytes_never_raise_and_every_line_is_accounted_for(junk, cuts, fmt):
    data = junk + b"\n"
    c = codec(fmt=fmt, max_line=32, time_field=0, time_max=1e6)
    out, i = [], 0
    for n in [*cuts, len(data)]:
        out += c.feed(data[i:i + n])
        i += n
        assert c.buffered <= 33
    s = c.stats
    assert s.bytes_in == len(data) and s.frames == len(out) and c.buffered == 0
    assert s.frames + s.framing_errors + s.skipped_lines == data.count(b"\n")


@settings(max_examples=150, deadline=None)
@given(st.lists(good_csv, min_size=2, max_size=20), st.integers(0, 10_000), st.binary(min_size=1, max_size=60),
       st.lists(st.integers(1, 40), max_size=10))
def test_garbage_inside_a_stream_costs_only_the_lines_it_touches(lines, where, garbage, cuts):
    data = b"".join(x + b"\n" for x in lines)
    at = where % len(data)
    bad = data[:at] + garbage + data[at:]
    ref = codec(fmt="csv", time_field=0, time_max=2.0 ** 32)
    want = ref.feed(data)
    c = codec(fmt="csv", time_field=0, time_max=2.0 ** 32)
    out, i = [], 0
    for n in [*cuts, len(bad)]:
        out += c.feed(bad[i:i + n])
        i += n
    before = data[:at].count(b"\n")  # lines complete before the garbage
    after_start = data.find(b"\n", at) + 1  # lines starting after the line the garbage fell in
    after = data[after_start:].count(b"\n") if after_start else 0
    assert out[:before] == want[:before]
    if after:
        assert out[len(out) - after:] == want[len(want) - after:]
    s = c.stats
    assert s.frames + s.framing_errors + s.skipped_lines == bad.count(b"\n")


# -- the vectorised CSV decoder -------------------------------------------------------------------------
plain = st.from_regex(r"[+-]?[0-9]{0,9}(\.[0-9]{0,9})?", fullmatch=True)
blank = st.sampled_from(["", "", " ", "\t"])


@settings(max_examples=300, deadline=None)
@given(st.lists(st.tuples(plain, plain, plain, blank, st.booleans()), min_size=1, max_size=15))
def test_feed_clean_equals_feed_bit_for_bit_or_declines(rows):
    """On arbitrary strings of digits, signs and points (many of them not numbers) the vectorised
    decoder either declines or gives exactly the per-line values."""
    data = b"".join(f"{a}{sp},{sp}{b},{c}{sp}".encode() + (b"\r\n" if crlf else b"\n") for a, b, c, sp, crlf in rows)
    ref = codec(fmt="csv", columns=("x", None, "z"))
    want = ref.feed(data)
    c = codec(fmt="csv", columns=("x", None, "z"))
    got = c.feed_clean(data)
    if got is None:
        assert c.stats.bytes_in == 0 and c.stats.frames == 0
        return
    vals, nl = got
    assert np.array([f.values for f in want]).tobytes() == vals.tobytes()
    assert nl.tolist() == [i for i, ch in enumerate(data) if ch == 10]
    assert c.stats.as_dict() == ref.stats.as_dict()


def test_feed_clean_parses_a_long_run_in_blocks_with_the_same_result(monkeypatch):
    """Long replays are parsed in blocks of whole lines; block edges (here every 32 bytes, lines of
    many lengths, one line longer than a block) change nothing, and a bad line in a late block
    still declines the whole run."""
    from devices.codecs import textline as tl
    rng = np.random.default_rng(5)
    rows = [f"{i},{rng.normal() * 10 ** rng.integers(0, 5):.{rng.integers(0, 6)}f},{rng.integers(-999, 999)}\n"
            for i in range(3000)]
    rows[1500] = "1500," + "9" * 14 + ".5,-" + "7" * 15 + "\n"  # 42 bytes: longer than a block
    data = "".join(rows).encode()
    whole = tl._parse_csv_block(data, 3)
    monkeypatch.setattr(tl, "_PARSE_BLOCK", 32)
    blocked = tl._parse_plain_csv(data, 3)
    assert whole is not None and blocked is not None
    assert whole[0].tobytes() == blocked[0].tobytes() and np.array_equal(whole[1], blocked[1])
    c = codec(fmt="csv", columns=("t", "a", "b"))
    assert np.array([f.values for f in c.feed(data)]).tobytes() == blocked[0].tobytes()
    assert tl._parse_plain_csv(data + b"1,2\n" + data, 3) is None


@settings(max_examples=100, deadline=None)
@given(st.lists(st.tuples(st.integers(0, 2 ** 32 - 1), st.floats(-1e5, 1e5, allow_nan=False),
                          st.integers(0, 9), st.integers(-10 ** 12, 10 ** 12)), min_size=1, max_size=30))
def test_feed_clean_takes_typical_sketch_output(rows):
    lines = [f"{t},{v:.{p}f},{k}\n".encode() for t, v, p, k in rows]
    data = b"".join(lines)
    ref = codec(fmt="csv", columns=("t", "a", "b"), time_field=0, time_max=2.0 ** 32)
    want = ref.feed(data)
    c = codec(fmt="csv", columns=("t", "a", "b"), time_field=0, time_max=2.0 ** 32)
    got = c.feed_clean(data)
    assert got is not None
    assert np.array([f.values for f in want]).tobytes() == got[0].tobytes()


def test_feed_clean_declines_what_it_does_not_handle():
    c = codec(fmt="csv")
    for data in (b"1,2,3,4", b"1,2,3,4\nt,ax,ay,az\n", b"1e3,2,3,4\n", b"1,2,3,4,\n", b"1 2 3 4\n", b"1,2,3\n",
                 b"1,2,3,4\n\n", b"12345678901234567890,2,3,4\n", b"1,2,3,4\r\r\n"):
        assert c.feed_clean(data) is None, data
    assert codec(fmt="kv").feed_clean(b"1,2,3,4\n") is None
    assert codec(fmt="csv", max_line=16).feed_clean(b"1,2,3,4\n" + b"1" * 18) is None  # feed drops that tail


def test_feed_clean_completes_a_pending_line_and_keeps_a_partial_one_like_feed():
    ref, c = codec(fmt="csv"), codec(fmt="csv")
    assert ref.feed(b"1,2") == [] and c.feed(b"1,2") == []
    want = ref.feed(b",3,4\n5,6.5,7,8\r\n9,1")
    vals, nl = c.feed_clean(b",3,4\n5,6.5,7,8\r\n9,1")
    assert vals.tolist() == [list(f.values) for f in want] == [[1, 2, 3, 4], [5, 6.5, 7, 8]]
    assert nl.tolist() == [4, 15]  # offsets of the newlines in the bytes given
    assert c.buffered == ref.buffered == 3 and c.stats.as_dict() == ref.stats.as_dict()
    assert c.feed(b",2,3\n") == ref.feed(b",2,3\n") == [TextFrame((9.0, 1.0, 2.0, 3.0), 15)]


# -- the device end to end: per-chunk path and batch path -------------------------------------------------
def sketch_chunks(n: int, seed: int, bad_every: int = 0, kv: bool = False, drop: int = 0) -> list[Chunk]:
    lay = TextLineLayout({**EXAMPLE, "format": "kv" if kv else "csv", "rate": "200"})
    rng = np.random.default_rng(seed)
    t = np.arange(n) / 200.0
    ch = {k: rng.normal(0, 5, n) for k in ("ax", "ay", "az", "gx", "gy", "gz")}
    lines = lay.encode_lines(ch, t, decimals=4)  # as Serial.print(x, 4) does
    if drop:
        del lines[n // 2:n // 2 + drop]
    if bad_every:
        for k in range(len(lines) - 1, 0, -bad_every):
            lines.insert(k, [b"MPU6050 ready\n", b"1,2,x\n", b"\xff\xfe\n"][k % 3])
    data = b"".join(lines)
    out, i, k = [], 0, 0
    while i < len(data):
        m = int(rng.integers(1, 120))
        out.append(Chunk(data[i:i + m], 3_000_000_000 + k * 2_000_000 + int(rng.integers(0, 500_000))))
        i += m
        k += 1
    return out


def flatten(items) -> dict[str, list[tuple]]:
    res: dict[str, list[tuple]] = {}
    for it in items:
        rows = [it] if type(it) is Sample else list(it.samples()) if type(it) is SampleBatch else []
        for s in rows:
            res.setdefault(s.stream, []).append((s.seq, s.t_host_ns, s.t_device_ns, s.t_bus_ns,
                                                 np.array(s.values).tobytes()))
    return res


@pytest.mark.parametrize("bad_every,kv,drop", [(0, False, 0), (97, False, 3), (0, True, 0)])
def test_batch_path_equals_per_chunk_path(bad_every, kv, drop):
    chunks = sketch_chunks(3000, seed=bad_every + kv, bad_every=bad_every, kv=kv, drop=drop)
    opts = {**EXAMPLE, "format": "auto", "rate": "200"}
    da, db = device(**opts), device(**opts)
    ref = flatten([x for c in chunks for x in da.process_chunk(c)])
    items = []
    for k in range(0, len(chunks), 211):
        items += db.process_chunks(ChunkRun.from_chunks(chunks[k:k + 211]))
    got = flatten(items)
    assert ref.keys() == got.keys() == {"s/imu"}
    assert len(ref["s/imu"]) == 3000 - drop
    assert got["s/imu"] == ref["s/imu"]
    assert da.codec.stats.as_dict() == db.codec.stats.as_dict()
    assert da.stats.lost_readings == db.stats.lost_readings == drop
    assert any(type(x) is SampleBatch for x in items) == (not kv)  # clean CSV takes the vectorised path
    if bad_every:
        assert da.codec.stats.skipped_lines >= 10 and da.codec.stats.framing_errors >= 20


def test_encoded_lines_decode_to_the_physical_values():
    for fmt in ("csv", "kv"):
        lay = TextLineLayout({**EXAMPLE, "format": fmt, "time_wrap": "u32"})
        d = device(**{**EXAMPLE, "format": fmt, "time_wrap": "u32"})
        vals = {"ax": 1.5, "ay": -9.80665, "az": 0.125, "gx": 0.3, "gy": -2.0, "gz": 1e-3}
        line = lay.encode_line(vals, t_device_s=12.345)
        (imu,) = samples(d.process_chunk(Chunk(line, 1)), "s/imu")
        assert imu.values == pytest.approx(tuple(vals.values()), rel=1e-12)
        assert imu.t_device_ns == 12_345_000_000
    lay = TextLineLayout({**EXAMPLE, "format": "kv"})
    assert lay.encode_line({"ax": 9.80665}, t_device_s=0.001) == b"t:1 ax:1\n"
    assert TextLineLayout(EXAMPLE).encode_line({"ax": 9.80665}, t_device_s=0.001) == b"1,1,nan,nan,nan,nan,nan\n"
    with pytest.raises(ValueError, match="t_device_s"):
        lay.encode_line({"ax": 1.0})
    with pytest.raises(ValueError, match="not in this layout"):
        lay.encode_line({"qx": 1.0}, 0.0)
    assert format_number(-0.0) == "-0" and float(format_number(0.1 + 0.2)) == 0.1 + 0.2


# -- option errors ----------------------------------------------------------------------------------------
@pytest.mark.parametrize("opts,message", [
    ({"columns": "t,ax", "units": "ms,furlong", "time": "t"}, "unknown unit 'furlong' for acceleration"),
    ({"columns": "gx", "units": "m/s^2"}, "unknown unit 'm/s\\^2' for angular rate"),
    ({"columns": "ax,ay", "time": "t"}, "time column 't' is not in columns=ax,ay"),
    ({"columns": "t,ax", "time": "t"}, "time column 't' needs a unit"),
    ({"columns": "t,ax", "units": "min,g", "time": "t"}, "unknown time unit 'min'"),
    ({"columns": "t,ax,ay", "units": "ms,g"}, "units= has 2 entries but columns= has 3"),
    ({"columns": "t,ax", "units": "ms,g", "time": "t", "time_wrap": "often"}, "time_wrap='often' is not u32"),
    ({"columns": "ax", "time_wrap": "u32"}, "time_wrap= needs a time column"),
    ({"columns": "ax,ax"}, "channel 'ax' is mapped twice"),
    ({"columns": "_,,_"}, "maps no column"),
    ({"columns": "t", "units": "ms", "time": "t"}, "maps only the time column"),
    ({"columns": "a b"}, "column key 'a b'"),
    ({"format": "json"}, "format='json' must be one of csv\\|kv\\|auto"),
    ({"baud": "115200"}, "unknown option 'baud'"),
])
def test_option_errors_are_config_errors_that_say_what_is_wrong(opts, message):
    with pytest.raises(ConfigError, match=message):
        device(**opts)
