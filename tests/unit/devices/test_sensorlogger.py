"""Sensor Logger HTTP push: the codec (the documented schema, round trips, unknown sensor names
counted and logged once, malformed / oversized / wrong-typed input counted and dropped, strict
mode) and ``SensorLoggerPhone`` (streams, platform signs, hPa -> Pa, nulls as NaN, messageId gaps
and duplicates, new sessions, time order, the replay property)."""

from __future__ import annotations

import itertools
import json
import logging
import math

import pytest

from capture.errors import ConfigError, ProtocolError
from capture.sample import Chunk, Sample
from devices.codecs.phone_json import (
    SENSORLOGGER_FIELDS,
    SL_MAX_BYTES,
    SL_MAX_ENTRIES,
    SensorEntry,
    SensorLoggerCodec,
    SensorLoggerMessage,
)
from devices.phone import SENSORLOGGER_CLOCK, SensorLoggerPhone
from devices.transports import open_transport

NAN = float("nan")
T0 = 1_698_501_144_401_773_000  # the schema example's time, ns
H0 = 10**12


def device(**opts) -> SensorLoggerPhone:
    return SensorLoggerPhone("sl", open_transport("loop://"), opts)


def samples(items, stream: str | None = None) -> list[Sample]:
    return [x for x in items if isinstance(x, Sample) and (stream is None or x.stream == f"sl/{stream}")]


def same(a: tuple, b: tuple) -> bool:
    return len(a) == len(b) and all(x == y or (math.isnan(x) and math.isnan(y)) for x, y in zip(a, b, strict=True))


def motion_message(mid: int, t0: int, n: int = 5, period_ns: int = 10_000_000,
                   session: str = "s1") -> SensorLoggerMessage:
    """n samples of accelerometer, gyroscope, gravity, magnetometer and orientation."""
    ents = []
    for k in range(n):
        t = t0 + k * period_ns
        ents += [SensorEntry("accelerometer", t, (0.01 * k, -0.02, 0.5)),
                 SensorEntry("gyroscope", t + 1000, (0.1, 0.2 * k, -0.3)),
                 SensorEntry("gravity", t, (0.0, 0.5, 9.79)),
                 SensorEntry("magnetometer", t + 2000, (20.0, -5.0, -40.0), 3),
                 SensorEntry("orientation", t + 3000, (0.9, 0.1, 0.2, 0.3, 0.01, 0.02, 0.03))]
    return SensorLoggerMessage(mid, session, "dev-1", tuple(ents))


def chunk(msg: SensorLoggerMessage, host: int | None = None) -> Chunk:
    last = max((e.time for e in msg.entries), default=T0)
    return Chunk(SensorLoggerCodec().encode(msg), H0 + (last - T0) + 30_000_000 if host is None else host)


# -- codec -------------------------------------------------------------------------------------
def test_the_documented_schema_decodes():
    body = {"messageId": 0, "sessionId": "identifier", "deviceId": "identifier", "payload": [
        {"name": "accelerometer", "time": 1698501144401773000, "values": {"z": 0.5, "y": -0.25, "x": 0.125}},
        {"name": "location", "time": 1698501145514000000, "values": {"latitude": 51.5, "longitude": -0.1}},
        {"name": "orientation", "time": 1698501144401773001,
         "values": {"yaw": 0.3, "qx": 0.1, "qz": 0.3, "roll": 0.1, "qw": 0.9, "qy": 0.2, "pitch": 0.2}},
        {"name": "magnetometer", "time": 1698501144401773002, "values": {"x": 1, "y": 2, "z": 3}, "accuracy": 3},
        {"name": "barometer", "time": 1698501144401773003, "values": {"relativeAltitude": 1.5, "pressure": 1013.25}},
    ]}
    c = SensorLoggerCodec()
    (m,) = c.feed(json.dumps(body).encode())
    assert (m.message_id, m.session_id, m.device_id) == (0, "identifier", "identifier")
    assert m.entries == (
        SensorEntry("accelerometer", 1698501144401773000, (0.125, -0.25, 0.5)),
        SensorEntry("orientation", 1698501144401773001, (0.9, 0.1, 0.2, 0.3, 0.1, 0.2, 0.3)),
        SensorEntry("magnetometer", 1698501144401773002, (1.0, 2.0, 3.0), 3),
        SensorEntry("barometer", 1698501144401773003, (1013.25, 1.5)),
    )
    assert m.entries[1].fields == ("qw", "qx", "qy", "qz", "roll", "pitch", "yaw")
    assert c.unknown_names == {"location": 1} and c.stats.errors == 0 and c.stats.frames == 1


def test_round_trip():
    c = SensorLoggerCodec()
    ents = tuple(SensorEntry(n, T0 + i, tuple(0.5 + i + k for k in range(len(f))), i if i % 2 else None)
                 for i, (n, (f, _)) in enumerate(SENSORLOGGER_FIELDS.items()))
    m = SensorLoggerMessage(41, "sess", "dev", ents)
    data = c.encode(m)
    assert c.feed(data) == [m]
    assert c.encode(c.feed(data)[0]) == data
    # NaN: required values go out as null, optional ones are left out; both come back as NaN
    m2 = SensorLoggerMessage(42, "sess", "dev", (SensorEntry("accelerometer", T0, (NAN, 1.0, 2.0)),
                                                  SensorEntry("orientation", T0, (1.0, 0.0, 0.0, 0.0, NAN, NAN, NAN))))
    data = c.encode(m2)
    d = json.loads(data)
    assert d["payload"][0]["values"]["x"] is None and set(d["payload"][1]["values"]) == {"qw", "qx", "qy", "qz"}
    (back,) = c.feed(data)
    assert all(same(a.values, b.values) for a, b in zip(back.entries, m2.entries, strict=True))
    assert SensorLoggerMessage(0, "s", "d") == c.feed(c.encode(SensorLoggerMessage(0, "s", "d")))[0]  # empty payload
    with pytest.raises(TypeError):
        c.encode({"messageId": 1})
    assert c.stats.errors == 0


def test_unknown_names_are_counted_and_logged_once(caplog):
    c = SensorLoggerCodec()
    body = {"messageId": 0, "sessionId": "s", "deviceId": "d", "payload": [
        {"name": "battery", "time": T0, "values": {"batteryLevel": 0.5, "batteryState": "charging"}},
        {"name": "network", "time": T0, "values": {"type": "wifi"}},
        {"name": "battery", "time": T0 + 1, "values": {}},
        {"name": "gyroscope", "time": T0, "values": {"x": 0, "y": 0, "z": 0}},
    ]}
    with caplog.at_level(logging.INFO, logger="devices.codecs.phone_json"):
        (m,) = c.feed(json.dumps(body).encode())
        c.feed(json.dumps(body).encode())
    assert [e.name for e in m.entries] == ["gyroscope"]
    assert c.unknown_names == {"battery": 4, "network": 2} and c.stats.errors == 0
    assert sum("'battery'" in r.message for r in caplog.records) == 1
    assert sum("'network'" in r.message for r in caplog.records) == 1
    # the table of names is bounded
    many = {"messageId": 1, "sessionId": "s", "deviceId": "d",
            "payload": [{"name": f"sensor{i}", "time": T0} for i in range(200)]}
    c.feed(json.dumps(many).encode())
    assert len(c.unknown_names) <= 65 and c.unknown_names["<other>"] > 100


BAD_MESSAGES = [
    (b"", "not JSON"),
    (b"{", "not JSON"),
    (b"\xc3\x28", "not UTF-8"),
    (b"[]", "not an object"),
    (b"null", "not an object"),
    (b'{"sessionId":"s","deviceId":"d","payload":[]}', "messageId is null"),
    (b'{"messageId":true,"sessionId":"s","deviceId":"d","payload":[]}', "messageId is a boolean"),
    (b'{"messageId":"1","sessionId":"s","deviceId":"d","payload":[]}', "messageId is a string"),
    (b'{"messageId":-3,"sessionId":"s","deviceId":"d","payload":[]}', "out of range"),
    (b'{"messageId":1,"sessionId":5,"deviceId":"d","payload":[]}', "sessionId"),
    (b'{"messageId":1,"sessionId":"s","deviceId":null,"payload":[]}', "deviceId"),
    (b'{"messageId":1,"sessionId":"s","deviceId":"d","payload":{}}', "payload is an object"),
    (b'{"messageId":1,"sessionId":"s","deviceId":"d"}', "payload is null"),
    (b'{"messageId":NaN,"sessionId":"s","deviceId":"d","payload":[]}', "non-finite"),
]


@pytest.mark.parametrize("data,why", BAD_MESSAGES)
def test_bad_messages_are_counted_and_dropped(data, why, caplog):
    c = SensorLoggerCodec()
    assert c.feed(data) == []
    assert c.stats.framing_errors == 1 and c.stats.frames == 0 and c.stats.skipped_bytes == len(data)
    assert why in caplog.text
    assert c.feed(b'{"messageId":1,"sessionId":"s","deviceId":"d","payload":[]}') == [SensorLoggerMessage(1, "s", "d")]
    with pytest.raises(ProtocolError):
        SensorLoggerCodec(strict=True).feed(data)


def test_oversized_messages_are_dropped():
    c = SensorLoggerCodec()
    e = {"name": "gyroscope", "time": T0, "values": {"x": 0, "y": 0, "z": 0}}
    ok = json.dumps({"messageId": 0, "sessionId": "s", "deviceId": "d", "payload": [e] * SL_MAX_ENTRIES}).encode()
    assert len(c.feed(ok)[0].entries) == SL_MAX_ENTRIES
    too_many = json.dumps({"messageId": 1, "sessionId": "s", "deviceId": "d",
                           "payload": [e] * (SL_MAX_ENTRIES + 1)}).encode()
    assert c.feed(too_many) == [] and c.stats.framing_errors == 1
    big = b'{"messageId":2,"sessionId":"' + b"s" * SL_MAX_BYTES + b'","deviceId":"d","payload":[]}'
    assert c.feed(big) == [] and c.stats.framing_errors == 2


BAD_ENTRIES = [
    5,
    [1, 2],
    {"time": T0, "values": {"x": 0, "y": 0, "z": 0}},                       # no name
    {"name": 7, "time": T0, "values": {"x": 0, "y": 0, "z": 0}},
    {"name": "gyroscope", "values": {"x": 0, "y": 0, "z": 0}},             # no time
    {"name": "gyroscope", "time": "1", "values": {"x": 0, "y": 0, "z": 0}},
    {"name": "gyroscope", "time": -1, "values": {"x": 0, "y": 0, "z": 0}},
    {"name": "gyroscope", "time": 1.5, "values": {"x": 0, "y": 0, "z": 0}},
    {"name": "gyroscope", "time": 2**63, "values": {"x": 0, "y": 0, "z": 0}},
    {"name": "gyroscope", "time": T0, "values": [0, 0, 0]},
    {"name": "gyroscope", "time": T0},
    {"name": "gyroscope", "time": T0, "values": {"x": 0, "y": 0}},           # no z
    {"name": "gyroscope", "time": T0, "values": {"x": "0", "y": 0, "z": 0}},
    {"name": "gyroscope", "time": T0, "values": {"x": False, "y": 0, "z": 0}},
    {"name": "gyroscope", "time": T0, "values": {"x": 0, "y": 0, "z": 0}, "accuracy": "high"},
    {"name": "orientation", "time": T0, "values": {"qx": 0, "qy": 0, "qz": 0}},  # no qw
    {"name": "barometer", "time": T0, "values": {"relativeAltitude": 0}},        # no pressure
]


@pytest.mark.parametrize("bad", BAD_ENTRIES)
def test_a_bad_entry_is_dropped_alone(bad):
    good = {"name": "gyroscope", "time": T0, "values": {"x": 0.5, "y": 0, "z": 0}}
    data = json.dumps({"messageId": 3, "sessionId": "s", "deviceId": "d", "payload": [good, bad, good]}).encode()
    c = SensorLoggerCodec()
    (m,) = c.feed(data)
    assert m.entries == (SensorEntry("gyroscope", T0, (0.5, 0.0, 0.0)),) * 2
    assert c.stats.framing_errors == 1 and c.stats.frames == 1
    with pytest.raises(ProtocolError):
        SensorLoggerCodec(strict=True).feed(data)


def test_integral_float_times_and_nulls_are_accepted():
    c = SensorLoggerCodec()
    (m,) = c.feed(b'{"messageId":0,"sessionId":"s","deviceId":"d","payload":['
                  b'{"name":"gravity","time":1.5e18,"values":{"x":null,"y":1,"z":2},"accuracy":null}]}')
    (e,) = m.entries
    assert e.time == 1_500_000_000_000_000_000 and same(e.values, (NAN, 1.0, 2.0)) and e.accuracy is None


# -- device --------------------------------------------------------------------------------------
def test_streams_and_options():
    d = device()
    names = [s.name.split("/")[1] for s in d.streams]
    assert names == ["acc", "gyro", "phone_gravity", "mag", "attitude", "total_acc", "baro"]
    kinds = {s.name.split("/")[1]: s.kind for s in d.streams}
    assert kinds == {"acc": "acc", "gyro": "gyro", "phone_gravity": "acc", "mag": "mag", "attitude": "quat",
                     "total_acc": "acc", "baro": "baro"}
    by = {s.name.split("/")[1]: s for s in d.streams}
    assert by["attitude"].channels == ("w", "x", "y", "z") and by["mag"].units == ("uT",) * 3
    assert by["gyro"].units == ("rad/s",) * 3 and by["acc"].units == ("m/s^2",) * 3
    assert by["baro"].units == ("Pa", "m") and by["baro"].nominal_rate_hz is None
    assert all(s.clock == SENSORLOGGER_CLOCK for s in d.streams) and SENSORLOGGER_CLOCK.tick_hz == 1e9
    assert by["acc"].nominal_rate_hz == 100.0 and device(rate=50).streams[0].nominal_rate_hz == 50.0
    assert not {"orientation", "gravity", "linear_acc"} & set(names)  # the fusion processor's names
    with pytest.raises(ConfigError):
        device(platform="windows")


def test_entries_become_samples_with_their_own_times():
    m = motion_message(0, T0)
    d = device()
    items = d.process_chunk(chunk(m))
    acc, gyro, grav, mag, att = (samples(items, s) for s in ("acc", "gyro", "phone_gravity", "mag", "attitude"))
    assert len(acc) == len(gyro) == len(grav) == len(mag) == len(att) == 5
    # device time = the entry's time (the clock sync unwraps ticks in float64: exact to 256 ns at 1.7e18 ns)
    assert [s.t_device_ns for s in acc] == pytest.approx([T0 + k * 10_000_000 for k in range(5)], abs=128)
    assert [s.t_device_ns for s in gyro] == pytest.approx([T0 + k * 10_000_000 + 1000 for k in range(5)], abs=128)
    assert acc[2].values == (0.02, -0.02, 0.5) and gyro[3].values == (0.1, 0.6000000000000001, -0.3)
    assert grav[0].values == (0.0, 0.5, 9.79) and mag[0].values == (20.0, -5.0, -40.0)
    assert att[0].values == (0.9, 0.1, 0.2, 0.3)  # qw qx qy qz
    host = chunk(m).t_ns
    assert all(s.t_bus_ns <= host for s in samples(items))


def test_platform_ios_negates_accelerations_only_and_baro_is_in_pa():
    m = SensorLoggerMessage(0, "s", "d", (
        SensorEntry("accelerometer", T0, (1.0, -2.0, 3.0)),
        SensorEntry("gravity", T0, (0.0, 0.0, -9.8)),
        SensorEntry("totalacceleration", T0, (0.5, 0.5, -9.8)),
        SensorEntry("gyroscope", T0, (0.1, 0.2, 0.3)),
        SensorEntry("magnetometer", T0, (10.0, 20.0, 30.0)),
        SensorEntry("barometer", T0, (1013.25, 2.5)),
        SensorEntry("gyroscopeuncalibrated", T0, (0.1, 0.2, 0.3)),
    ))
    std = device().process_chunk(chunk(m))
    ios = device(platform="ios").process_chunk(chunk(m))
    assert samples(std, "acc")[0].values == (1.0, -2.0, 3.0)
    assert samples(ios, "acc")[0].values == (-1.0, 2.0, -3.0)
    assert samples(ios, "phone_gravity")[0].values == (-0.0, -0.0, 9.8)  # flat, screen up: +z
    assert samples(ios, "total_acc")[0].values == (-0.5, -0.5, 9.8)
    for name in ("gyro", "mag", "baro"):
        assert samples(ios, name)[0].values == samples(std, name)[0].values
    assert samples(std, "baro")[0].values == (101325.0, 2.5)
    d = device(platform="android")
    assert samples(d.process_chunk(chunk(m)), "acc")[0].values == (1.0, -2.0, 3.0)
    assert d.health()["unused_entries"] == 1  # the uncalibrated gyroscope has no stream


def test_nulls_become_nan():
    m = SensorLoggerMessage(0, "s", "d", (SensorEntry("accelerometer", T0, (NAN, 1.0, NAN)),))
    (s,) = samples(device(platform="ios").process_chunk(chunk(m)), "acc")
    assert same(s.values, (NAN, -1.0, NAN))


def test_entries_are_emitted_in_time_order_whatever_their_message_order():
    m = motion_message(0, T0, n=6)
    shuffled = SensorLoggerMessage(0, "s1", "dev-1", tuple(reversed(m.entries)))
    items = device().process_chunk(chunk(shuffled))
    for name in ("acc", "gyro", "phone_gravity", "mag", "attitude"):
        ss = samples(items, name)
        assert [s.t_device_ns for s in ss] == sorted(s.t_device_ns for s in ss)
        assert all(a.t_bus_ns <= b.t_bus_ns for a, b in itertools.pairwise(ss))
    acc = samples(items, "acc")
    assert [s.values[0] for s in acc] == [0.01 * k for k in range(6)]
    # and across streams the bus times follow the device times
    all_s = sorted(samples(items), key=lambda s: s.t_device_ns)
    assert all(a.t_bus_ns <= b.t_bus_ns for a, b in itertools.pairwise(all_s))


def test_message_id_gaps_duplicates_and_late_messages():
    d = device()
    period = 50_000_000
    msgs = {i: motion_message(i, T0 + i * 5 * period, n=5, period_ns=period // 5) for i in range(8)}
    order = [0, 1, 1, 4, 3, 5, 5, 7]  # 1 repeated (a retried POST), 2 and 3 lost, 3 late, 5 repeated, 6 lost
    out = []
    for i in order:
        out += d.process_chunk(chunk(msgs[i]))
    h = d.health()
    assert h["lost_messages"] == 3 and h["duplicate_messages"] == 2 and h["late_messages"] == 1
    acc = samples(out, "acc")
    assert len(acc) == 5 * 5  # messages 0, 1, 4, 5, 7 once each
    assert [s.t_device_ns for s in acc] == sorted({s.t_device_ns for s in acc})
    assert h["clock_resets"] == 0 and h["framing_errors"] == 0


def test_a_new_session_starts_message_ids_again():
    d = device()
    d.process_chunk(chunk(motion_message(5, T0)))
    d.process_chunk(chunk(motion_message(6, T0 + 10**8)))
    items = d.process_chunk(chunk(motion_message(0, T0 + 2 * 10**8, session="s2")))
    assert len(samples(items, "acc")) == 5
    h = d.health()
    assert h["sessions"] == 2 and h["lost_messages"] == 0 and h["duplicate_messages"] == 0
    assert d.info == {"session_id": "s2", "device_id": "dev-1"}


def test_bad_bodies_never_raise_and_unknown_names_show_in_health():
    d = device()
    items = d.process_chunk(Chunk(b"<html>", H0))
    assert samples(items) == [] and d.health()["framing_errors"] == 1
    body = json.dumps({"messageId": 0, "sessionId": "s", "deviceId": "d", "payload": [
        {"name": "microphone", "time": T0, "values": {"dBFS": -40}}]}).encode()
    d.process_chunk(Chunk(body, H0))
    h = d.health()
    assert h["unknown_entries"] == 1 and h["unknown_names"] == {"microphone": 1}
    with pytest.raises(ProtocolError):
        SensorLoggerPhone("sl", open_transport("loop://"), {}, strict=True).process_chunk(Chunk(b"{}", H0))


def test_refeeding_the_same_chunks_gives_identical_samples():
    chunks = []
    for i in range(40):
        m = motion_message(i, T0 + i * 50_000_000, n=5)
        if i == 7:  # a null in the middle
            m = m._replace(entries=(SensorEntry("accelerometer", T0 + i * 50_000_000 + 1, (NAN, 0.0, NAN)),
                                    *m.entries))
        chunks.append(chunk(m, H0 + i * 50_000_000 + 30_000_000 + (i * 7919) % 13_000_000))
    first, dev = device(), device()
    a = [x for c in chunks for x in samples(first.process_chunk(c))]
    b = [x for c in chunks for x in samples(dev.process_chunk(c))]
    assert len(a) == len(b) == 40 * 25 + 1
    assert all(x[:5] == y[:5] and same(x.values, y.values) for x, y in zip(a, b, strict=True))
    assert dev.health()["lost_readings"] == 0 and dev.health()["lost_messages"] == 0
