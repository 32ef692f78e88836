"""The built-in phone page protocol: the codec (exact round trips, hand-written protocol messages,
malformed, oversized and wrong-typed input counted and dropped, strict mode) and ``PhonePage``
(stream layout, deg/s -> rad/s with alpha/beta/gamma -> x/y/z, nulls as NaN, seq gaps, hello and
pong bookkeeping, time order, and the replay property)."""

from __future__ import annotations

import itertools
import json
import math

import numpy as np
import pytest

from capture.errors import ConfigError, ProtocolError
from capture.sample import Chunk, Direction, Sample
from devices.codecs.phone_json import (
    MAX_ROWS,
    PAGE_MAX_BYTES,
    PageCodec,
    PageData,
    PageHello,
    PagePing,
    PagePong,
    PageWelcome,
)
from devices.phone import PAGE_CLOCK, PhonePage
from devices.transports import open_transport
from sim_devices.phone_sim import page_hello, page_messages, page_pong

NAN = float("nan")
T0 = 10**12  # host ns of the first chunk


def device(**opts) -> PhonePage:
    return PhonePage("ph", open_transport("loop://"), opts)


def samples(items, stream: str | None = None) -> list[Sample]:
    return [x for x in items if isinstance(x, Sample) and (stream is None or x.stream == f"ph/{stream}")]


def feed_all(dev: PhonePage, chunks: list[Chunk]) -> list:
    return [x for c in chunks for x in dev.process_chunk(c)]


def sim_chunks(duration_s: float = 3.0, **kw) -> list[Chunk]:
    msgs = page_messages(duration_s, **kw)
    out = [Chunk(page_hello(), T0, Direction.RX)]
    # arrival: the page clock's send time + 20 ms + up to 8 ms of jitter
    rnd = np.random.default_rng(3)
    for m in msgs:
        out.append(Chunk(m.data, T0 + int(m.sent_ms * 1e6) + 20_000_000 + int(rnd.uniform(0, 8e6)), Direction.RX))
    return out


def same(a: tuple, b: tuple) -> bool:
    return len(a) == len(b) and all(x == y or (math.isnan(x) and math.isnan(y)) for x, y in zip(a, b, strict=True))


# -- codec -------------------------------------------------------------------------------------
def test_protocol_example_messages_decode():
    c = PageCodec()
    hello = (b'{"type":"hello","v":1,"id":"k3j","ua":"Mozilla/5.0 (iPhone)","platform":"ios",'
             b'"screen":[390,844],"orient":0,"t":1234.5}')
    data = (b'{"type":"data","seq":7,"sent":2000.25,"orient":90,'
            b'"m":[[1990.1,0.1,-0.2,0.3,0.5,9.7,0.9,90,-45,180,16.67],[2006.8,null,null,null,0,9.8,0,0,0,0,null]],'
            b'"o":[[1991.0,359.5,12.25,-80,1]],"t":[[1995.5,0,3,120.5,300,0.5,11,12.5]]}')
    pong = b'{"type":"pong","h":123456789012,"t":2100.75}'
    (h,) = c.feed(hello)
    assert h == PageHello("k3j", "ios", "Mozilla/5.0 (iPhone)", (390.0, 844.0), 0.0, 1234.5, 1, None)
    (d,) = c.feed(data)
    assert isinstance(d, PageData) and d.seq == 7 and d.sent == 2000.25 and d.orient == 90.0
    assert d.motion[0] == (1990.1, 0.1, -0.2, 0.3, 0.5, 9.7, 0.9, 90.0, -45.0, 180.0, 16.67)
    assert same(d.motion[1], (2006.8, NAN, NAN, NAN, 0.0, 9.8, 0.0, 0.0, 0.0, 0.0, NAN))
    assert d.orientation == ((1991.0, 359.5, 12.25, -80.0, 1.0),)
    assert d.touches == ((1995.5, 0.0, 3.0, 120.5, 300.0, 0.5, 11.0, 12.5),)
    assert c.feed(pong) == [PagePong(123456789012, 2100.75)]
    assert c.stats.frames == 3 and c.stats.errors == 0 and c.buffered == 0


def test_round_trip_of_every_frame_type():
    c = PageCodec()
    frames = [
        PageHello("id-1", "android", "UA", (412.0, 915.0), 90.0, 12.5, 1, "tok"),
        PageHello("id-2", "other"),
        PageData(0),
        PageData(5, 100.5, -90.0, ((1.0, 0.1, 0.2, 0.3, 0.4, 9.8, 0.6, 1.5, -2.5, 3.5, 16.0),),
                 ((2.0, 10.0, 20.0, 30.0, 0.0),), ((3.0, 1.0, 42.0, 5.5, 6.5, 0.25, 0.0, 0.0),)),
        PagePong(-5, 0.125),
        PagePing(987654321),
        PageWelcome("phone-1", 1.0),
    ]
    for f in frames:
        data = c.encode(f)
        assert c.feed(data) == [f]
        assert c.encode(c.feed(data)[0]) == data
    # NaN goes out as null and comes back as NaN
    f = PageData(1, None, None, ((1.0, NAN, NAN, NAN, 0.0, 0.0, 9.8, NAN, 0.0, 0.0, NAN),),
                 ((2.0, NAN, 1.0, 2.0, NAN),))
    data = c.encode(f)
    assert b"NaN" not in data and json.loads(data)["m"][0][1] is None
    (g,) = c.feed(data)
    assert same(g.motion[0], f.motion[0]) and same(g.orientation[0], f.orientation[0])
    assert c.stats.errors == 0
    with pytest.raises(TypeError):
        c.encode({"type": "data"})


def test_the_simulator_encodes_what_it_says():
    c = PageCodec()
    msgs = page_messages(1.0, rate_hz=60.0, touches=True)
    assert len(msgs) == 20  # one message per 50 ms
    assert [m.frame.seq for m in msgs] == list(range(20))
    assert sum(len(m.frame.motion) for m in msgs) == 60
    for m in msgs:
        assert c.feed(m.data) == [m.frame]
        assert all(m.frame.sent >= r[0] for r in m.frame.motion)  # sent after its events
    assert c.stats.errors == 0


BAD_MESSAGES = [
    (b"", "not JSON"),
    (b"{not json", "not JSON"),
    (b"\xff\xfe{}", "not UTF-8"),
    (b"[1,2]", "not an object"),
    (b'"data"', "not an object"),
    (b'{"seq":1}', "message type"),
    (b'{"type":"bogus","seq":1}', "unknown message type 'bogus'"),
    (b'{"type":7}', "message type"),
    (b'{"type":"data"}', "seq"),
    (b'{"type":"data","seq":true}', "seq is a boolean"),
    (b'{"type":"data","seq":"3"}', "seq is a string"),
    (b'{"type":"data","seq":-1}', "out of range"),
    (b'{"type":"data","seq":1.5}', "not an integer"),
    (b'{"type":"data","seq":1,"m":{}}', '"m" is an object'),
    (b'{"type":"data","seq":1,"sent":NaN}', "non-finite"),
    (b'{"type":"data","seq":1,"sent":Infinity}', "non-finite"),
    (b'{"type":"data","seq":1,"sent":"x"}', "sent is a string"),
    (b'{"type":"hello","v":2,"id":"a","platform":"ios"}', "version 2"),
    (b'{"type":"hello","v":1,"id":"a","platform":"windows"}', "platform"),
    (b'{"type":"hello","v":1,"id":5,"platform":"ios"}', "id is the number 5"),
    (b'{"type":"hello","v":1,"id":"a","platform":"ios","screen":[1]}', "screen"),
    (b'{"type":"pong","h":"1","t":2}', "pong h"),
    (b'{"type":"pong","h":1}', "pong t"),
    (b"[" * 100_000 + b"]" * 100_000, "not JSON"),
    (b'{"type":"data","seq":1' + b'9' * 5000 + b'}', "not JSON"),
]


@pytest.mark.parametrize("data,why", BAD_MESSAGES)
def test_bad_messages_are_counted_and_dropped(data, why, caplog):
    c = PageCodec()
    assert c.feed(data) == []
    assert c.stats.framing_errors == 1 and c.stats.frames == 0 and c.stats.skipped_bytes == len(data)
    assert why in caplog.text
    # the next good message still decodes
    assert c.feed(b'{"type":"data","seq":2}') == [PageData(2)]
    strict = PageCodec(strict=True)
    with pytest.raises(ProtocolError):
        strict.feed(data)


def test_oversized_messages_and_too_many_rows_are_dropped():
    c = PageCodec()
    big = b'{"type":"data","seq":1,"pad":"' + b"x" * PAGE_MAX_BYTES + b'"}'
    assert c.feed(big) == [] and c.stats.framing_errors == 1
    row = [1.0, 0, 0, 0, 0, 0, 9.8, 0, 0, 0, 16]
    ok = json.dumps({"type": "data", "seq": 1, "m": [row] * MAX_ROWS}).encode()
    assert len(c.feed(ok)[0].motion) == MAX_ROWS
    too_many = json.dumps({"type": "data", "seq": 2, "m": [row] * (MAX_ROWS + 1)}).encode()
    assert c.feed(too_many) == [] and c.stats.framing_errors == 2


BAD_ROWS = [
    ("m", [1.0, 0, 0, 0, 0, 0, 9.8, 0, 0, 0]),           # 10 long
    ("m", [1.0, 0, 0, 0, 0, 0, 9.8, 0, 0, 0, 16, 0]),    # 12 long
    ("m", [None, 0, 0, 0, 0, 0, 9.8, 0, 0, 0, 16]),      # no time
    ("m", [-1.0, 0, 0, 0, 0, 0, 9.8, 0, 0, 0, 16]),      # negative time
    ("m", [1.0, "0", 0, 0, 0, 0, 9.8, 0, 0, 0, 16]),     # string
    ("m", [1.0, True, 0, 0, 0, 0, 9.8, 0, 0, 0, 16]),    # boolean
    ("m", [1.0, [0], 0, 0, 0, 0, 9.8, 0, 0, 0, 16]),     # array
    ("m", {"t": 1}),
    ("m", 5),
    ("o", [1.0, 10, 20, 30]),
    ("o", [1.0, 10, 20, 30, "yes"]),
    ("t", [1.0, 4, 1, 10, 10, 0, 0, 0]),                 # phase 4
    ("t", [1.0, 0.5, 1, 10, 10, 0, 0, 0]),               # fractional phase
    ("t", [1.0, 0, 1, None, 10, 0, 0, 0]),               # no x
    ("t", [1.0, 0, "a", 10, 10, 0, 0, 0]),               # string id
]


@pytest.mark.parametrize("key,bad", BAD_ROWS)
def test_a_bad_row_is_dropped_alone(key, bad):
    good = {"m": [2.0, 0.1, 0.2, 0.3, 0.0, 0.0, 9.8, 1.0, 2.0, 3.0, 16.0],
            "o": [2.0, 10.0, 20.0, 30.0, 1.0], "t": [2.0, 1.0, 1.0, 10.0, 10.0, 0.0, 0.0, 0.0]}
    msg = {"type": "data", "seq": 4, key: [good[key], bad, good[key]]}
    c = PageCodec()
    (f,) = c.feed(json.dumps(msg).encode())
    rows = {"m": f.motion, "o": f.orientation, "t": f.touches}[key]
    assert rows == (tuple(float(x) for x in good[key]),) * 2
    assert c.stats.framing_errors == 1 and c.stats.frames == 1
    with pytest.raises(ProtocolError):
        PageCodec(strict=True).feed(json.dumps(msg).encode())


def test_absolute_may_be_a_boolean_and_unknown_keys_are_ignored():
    c = PageCodec()
    (f,) = c.feed(b'{"type":"data","seq":0,"o":[[1,2,3,4,true],[2,2,3,4,false]],"extra":{"x":1}}')
    assert [r[4] for r in f.orientation] == [1.0, 0.0]
    assert c.stats.errors == 0


# -- device --------------------------------------------------------------------------------------
def test_streams_and_options():
    d = device()
    names = [s.name for s in d.streams]
    assert names == ["ph/imu", "ph/user_acc", "ph/attitude", "ph/touch"]
    imu, user, att, touch = d.streams
    assert imu.kind == "imu" and imu.channels == ("ax", "ay", "az", "gx", "gy", "gz")
    assert imu.units == ("m/s^2",) * 3 + ("rad/s",) * 3
    assert imu.frame == "phone frame: x right, y up the screen, z out of the screen (right-handed)"
    assert user.kind == "acc" and att.kind == "euler" and att.units == ("deg",) * 3 and touch.kind == "touch"
    assert touch.channels == ("phase", "id", "x", "y", "force", "rx", "ry")
    assert imu.nominal_rate_hz == user.nominal_rate_hz == 60.0
    assert att.nominal_rate_hz is None and touch.nominal_rate_hz is None
    assert all(s.clock == PAGE_CLOCK for s in d.streams) and PAGE_CLOCK.tick_hz == 1e6
    assert not {"ph/orientation", "ph/gravity", "ph/linear_acc"} & set(names)  # the fusion processor's names
    assert device(rate=100).streams[0].nominal_rate_hz == 100.0
    with pytest.raises(ConfigError):
        device(rate=0)
    with pytest.raises(ConfigError):
        device(bogus=1)


def test_devicemotion_becomes_imu_and_user_acc_with_rad_s_and_axis_mapping():
    d = device()
    msg = PageData(0, 30.0, 0.0, ((12.345678, 0.1, 0.2, 0.3, 1.0, 2.0, 9.0, 90.0, -180.0, 45.0, 16.0),))
    items = d.process_chunk(Chunk(PageCodec().encode(msg), T0))
    (imu,) = samples(items, "imu")
    (user,) = samples(items, "user_acc")
    assert imu.values[:3] == (1.0, 2.0, 9.0)  # accelerationIncludingGravity
    # rotationRate alpha (about x) -> gx, beta (y) -> gy, gamma (z) -> gz, deg/s -> rad/s
    assert imu.values[3:] == pytest.approx((math.pi / 2, -math.pi, math.pi / 4), rel=1e-15)
    assert user.values == (0.1, 0.2, 0.3)
    assert imu.t_device_ns == user.t_device_ns == 12_346_000  # ticks = round(t_ms * 1000) us
    assert imu.t_bus_ns <= T0


def test_nulls_become_nan_and_all_null_events_give_no_reading():
    d = device()
    rows = ((10.0, None, None, None, 0.0, None, 9.8, 1.0, None, 2.0, None),
            (26.0, None, None, None, None, None, None, None, None, None, None),  # desktop browser: nothing
            (42.0, 0.5, None, 0.25, None, None, None, None, None, None, 16.0))
    data = json.dumps({"type": "data", "seq": 0, "m": [list(r) for r in rows]}).encode()
    items = d.process_chunk(Chunk(data, T0))
    imu = samples(items, "imu")
    user = samples(items, "user_acc")
    assert len(imu) == 1 and len(user) == 1
    assert same(imu[0].values, (0.0, NAN, 9.8, math.radians(1.0), NAN, math.radians(2.0)))
    assert same(user[0].values, (0.5, NAN, 0.25)) and user[0].t_device_ns == 42_000_000


def test_invert_acc_flips_both_accelerations_only():
    msg = PageCodec().encode(PageData(0, None, None, ((5.0, 0.1, 0.2, 0.3, 1.0, 2.0, 9.0, 10.0, 20.0, 30.0, 16.0),)))
    a = device().process_chunk(Chunk(msg, T0))
    b = device(invert_acc=True).process_chunk(Chunk(msg, T0))
    ia, ib = samples(a, "imu")[0].values, samples(b, "imu")[0].values
    assert ib[:3] == tuple(-x for x in ia[:3]) and ib[3:] == ia[3:]
    assert samples(b, "user_acc")[0].values == (-0.1, -0.2, -0.3)


def test_simulated_waving_comes_out_complete_and_in_order():
    chunks = sim_chunks(3.0, touches=True)
    d = device()
    items = feed_all(d, chunks)
    msgs = page_messages(3.0, touches=True)
    rows = [r for m in msgs for r in m.frame.motion]
    imu = samples(items, "imu")
    assert len(imu) == len(rows) == 180 and len(samples(items, "user_acc")) == 180
    assert [s.t_device_ns for s in imu] == [round(r[0] * 1000) * 1000 for r in rows]
    for s, r in zip(imu, rows, strict=True):
        assert s.values == pytest.approx(r[4:7] + tuple(math.radians(x) for x in r[7:10]), rel=1e-14)
    assert [s.seq for s in imu] == list(range(180))
    # lying roughly flat, screen up: gravity reads +z
    assert np.mean([s.values[2] for s in imu]) > 5.0
    att = samples(items, "attitude")
    assert len(att) == 60 and all(0.0 <= s.values[0] < 360.0 for s in att)
    touch = samples(items, "touch")
    assert [s.values[0] for s in touch] == [0.0, 1, 1, 1, 1, 1, 2.0] and {s.values[1] for s in touch} == {7.0}
    for name in ("imu", "user_acc", "attitude", "touch"):
        ss = samples(items, name)
        assert all(a.t_device_ns < b.t_device_ns for a, b in itertools.pairwise(ss)), name
        assert all(a.t_bus_ns <= b.t_bus_ns for a, b in itertools.pairwise(ss)), name
        assert all(s.t_bus_ns <= s.t_host_ns for s in ss), name
    h = d.health()
    assert h["lost_messages"] == 0 and h["framing_errors"] == 0 and h["hellos"] == 1 and h["lost_readings"] == 0


def test_rows_out_of_order_in_a_message_are_emitted_in_time_order():
    rows = [[t, 0, 0, 0, 0, 0, 9.8, 0, 0, t, 16] for t in (50.0, 16.0, 33.0)]
    o = [[40.0, 1, 2, 3, 0], [20.0, 4, 5, 6, 0]]
    data = json.dumps({"type": "data", "seq": 0, "m": rows, "o": o}).encode()
    items = device().process_chunk(Chunk(data, T0))
    assert [s.t_device_ns for s in samples(items, "imu")] == [16_000_000, 33_000_000, 50_000_000]
    assert [s.values[5] for s in samples(items, "imu")] == [math.radians(x) for x in (16.0, 33.0, 50.0)]
    assert [s.values[0] for s in samples(items, "attitude")] == [4.0, 1.0]


def test_seq_gaps_count_lost_messages():
    msgs = page_messages(1.0)
    d = device()
    keep = [m for m in msgs if m.frame.seq not in (3, 4, 10)]
    feed_all(d, [Chunk(m.data, T0 + int(m.sent_ms * 1e6)) for m in keep])
    assert d.health()["lost_messages"] == 3
    # a reloaded page starts again at 0: a restart, not a loss
    again = page_messages(0.2, t0_ms=50.0)
    feed_all(d, [Chunk(m.data, T0 + 2 * 10**9 + int(m.sent_ms * 1e6)) for m in again])
    h = d.health()
    assert h["lost_messages"] == 3 and h["seq_restarts"] == 1


def test_hello_fills_info_without_readings_and_drops_the_token():
    d = device()
    items = d.process_chunk(Chunk(page_hello(page_id="abc", platform="ios", ua="iPhone UA", screen=(390, 844),
                                             orient=90.0, t=5.0, token="secret"), T0))
    assert samples(items) == []
    assert d.info["id"] == "abc" and d.info["platform"] == "ios" and d.info["ua"] == "iPhone UA"
    assert d.info["screen"] == (390.0, 844.0) and d.info["orient"] == 90.0
    assert "secret" not in repr(d.info)


def test_pongs_give_round_trip_and_offset():
    d = device()
    h = T0
    # the page answers 3 ms after the ping left; its clock reads 1000 ms at that moment = host T0 + 3 ms
    items = d.process_chunk(Chunk(page_pong(h, 1000.0), T0 + 6_000_000))
    assert samples(items) == []
    d.process_chunk(Chunk(page_pong(h + 10**9, 2000.0), T0 + 10**9 + 30_000_000))  # a slow one
    st = d.health()
    assert st["pongs"] == 2 and st["rtt_min_ns"] == 6_000_000 and st["rtt_last_ns"] == 30_000_000
    assert st["page_offset_ns"] == T0 + 3_000_000 - 1000 * 10**6


def test_bad_chunks_never_raise_and_are_reported():
    d = device()
    items = d.process_chunk(Chunk(b'{"type":"nope"}', T0))
    assert samples(items) == [] and d.health()["framing_errors"] == 1
    assert any(type(x).__name__ == "DeviceEvent" for x in items)
    strict = PhonePage("ph", open_transport("loop://"), {}, strict=True)
    with pytest.raises(ProtocolError):
        strict.process_chunk(Chunk(b"garbage", T0))


def test_refeeding_the_same_chunks_gives_identical_samples():
    chunks = sim_chunks(2.0, touches=True, null_acceleration=True)
    a = samples(feed_all(device(), chunks))
    b = samples(feed_all(device(), chunks))
    assert len(a) == len(b) > 100
    assert all(x[:5] == y[:5] and same(x.values, y.values) for x, y in zip(a, b, strict=True))
    assert samples(feed_all(device(), chunks), "user_acc") == []  # all-null acceleration
