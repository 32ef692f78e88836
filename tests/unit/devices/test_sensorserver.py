"""SensorServer (``SensorServerCodec``, ``SensorServerPhone``): Android sensor events as WebSocket
text frames, perfcap being the client of the app.

There are no real SensorServer recordings in ``../shared/traces``, so the messages here are written
from the documented format (``docs/design/phone-protocols.md`` section 2, after the app's
``SensorWebSocketServer.kt``): ``{"values":[...],"timestamp":ns,"accuracy":int}`` with ``"type"``
on the multi-sensor path, and ``{"action":..,"x":..,"y":..}`` touches.
"""

from __future__ import annotations

import json
import math
from urllib.parse import parse_qs, unquote, urlsplit

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from capture.errors import ConfigError, ProtocolError
from capture.sample import Chunk, DeviceEvent, Direction, EventKind, Sample
from devices.codecs.sensorserver import SS_MAX_BYTES, SensorServerCodec, SensorServerEvent, SensorServerTouch
from devices.phone_apps.sensorserver import SENSORSERVER_CLOCK, SensorServerPhone
from devices.transports import open_transport
from devices.transports.sensorserver import SENSORSERVER_CLOSE_CODES
from sim_devices.phone_apps_sim import sensorserver_event, sensorserver_touch

T0 = 123_456_789_000  # ns since boot
ACC = "android.sensor.accelerometer"
GYRO = "android.sensor.gyroscope"


def device(strict: bool = False, **opts) -> SensorServerPhone:
    return SensorServerPhone("ss", open_transport("loop://"), opts, strict=strict)


def run(dev: SensorServerPhone, frames: list[bytes], h0: int = 10**12, period: int = 5_000_000) -> list:
    out = []
    for i, d in enumerate(frames):
        out += dev.process_chunk(Chunk(d, h0 + i * period, Direction.RX))
    return out


def samples(items, stream: str | None = None) -> list[Sample]:
    return [x for x in items if isinstance(x, Sample) and (stream is None or x.stream == f"ss/{stream}")]


# -- paths and close codes ------------------------------------------------------------------------
def test_websocket_paths():
    assert SensorServerPhone.ws_path("accelerometer") == "/sensor/connect?type=android.sensor.accelerometer"
    p = SensorServerPhone.ws_path("accelerometer, android.sensor.Gyroscope,rotation_vector")
    parts = urlsplit(p)
    assert parts.path == "/sensors/connect"
    assert "[" not in p and '"' not in p  # URL-encoded
    assert json.loads(parse_qs(parts.query)["types"][0]) == [ACC, GYRO, "android.sensor.rotation_vector"]
    assert json.loads(unquote(p.split("=", 1)[1])) == [ACC, GYRO, "android.sensor.rotation_vector"]
    assert SensorServerPhone.ws_path(["touchscreen"]) == "/touchscreen"
    assert device(types="gyroscope,magnetic_field").path == SensorServerPhone.ws_path(["gyroscope", "magnetic_field"])


@pytest.mark.parametrize("types, what", [
    ("", "no sensor type"), ("accelerometer,barometer", "unknown sensor type 'barometer'"),
    ("gyroscope,android.sensor.gyroscope", "listed twice"), ("touchscreen,accelerometer", "connection of its own"),
])
def test_bad_types_are_config_errors(types, what):
    with pytest.raises(ConfigError, match=what):
        SensorServerPhone.ws_path(types)
    with pytest.raises(ConfigError, match=what):
        device(types=types)


def test_close_codes_4001_to_4009_are_explained():
    assert sorted(SensorServerPhone.CLOSE_CODES) == list(range(4001, 4010))
    assert SensorServerPhone.CLOSE_CODES is SENSORSERVER_CLOSE_CODES
    assert "sensor not found" in SensorServerPhone.close_reason(4001)
    assert "permission" in SensorServerPhone.close_reason(4009)
    assert SensorServerPhone.close_reason(1006) == "closed with code 1006"


# -- decoding -------------------------------------------------------------------------------------
def test_streams_follow_types_in_order():
    dev = device(types="rotation_vector,accelerometer,gyroscope,magnetic_field,gravity,linear_acceleration", rate=100)
    assert [(s.name, s.kind, s.channels[0]) for s in dev.streams] == [
        ("ss/attitude", "quat", "w"), ("ss/acc", "acc", "ax"), ("ss/gyro", "gyro", "gx"), ("ss/mag", "mag", "mx"),
        ("ss/phone_gravity", "acc", "ax"), ("ss/user_acc", "acc", "ax")]
    assert {s.clock for s in dev.streams} == {SENSORSERVER_CLOCK} and {s.nominal_rate_hz for s in dev.streams} == {100}
    assert device().streams[0].nominal_rate_hz is None  # rate unknown by default


def test_multi_sensor_events_decode_to_exact_values_and_device_times():
    dev = device(types="accelerometer,gyroscope,magnetic_field,rotation_vector,gravity,linear_acceleration")
    msgs = [
        b'{"values":[0.125,-0.25,9.75],"timestamp":123456789000,"accuracy":3,"type":"android.sensor.accelerometer"}',
        b'{"values":[0.5,0.25,-0.125],"timestamp":123456791500,"accuracy":3,"type":"android.sensor.gyroscope"}',
        b'{"values":[20.5,-4.25,-40.0],"timestamp":123456792000,"accuracy":2,"type":"android.sensor.magnetic_field"}',
        (b'{"values":[0.5,0.25,0.5,0.6614378,0.1],"timestamp":123456793000,"accuracy":3,'
         b'"type":"android.sensor.rotation_vector"}'),
        b'{"values":[0.5,0.25,0.5],"timestamp":123456794000,"accuracy":3,"type":"android.sensor.rotation_vector"}',
        b'{"values":[0.0,0.5,9.75],"timestamp":123456795000,"accuracy":3,"type":"android.sensor.gravity"}',
        b'{"values":[0.125,-0.75,0.0],"timestamp":123456796000,"accuracy":3,"type":"android.sensor.linear_acceleration"}',
        b'{"values":[0.25,-0.25,9.5],"timestamp":123466789000,"accuracy":3,"type":"ANDROID.SENSOR.ACCELEROMETER"}',
    ]
    items = run(dev, msgs)
    acc = samples(items, "acc")
    assert [s.values for s in acc] == [(0.125, -0.25, 9.75), (0.25, -0.25, 9.5)]
    assert [s.t_device_ns for s in acc] == [123456789000, 123466789000]
    assert samples(items, "gyro")[0].values == (0.5, 0.25, -0.125)
    assert samples(items, "gyro")[0].t_device_ns == 123456791500
    assert samples(items, "mag")[0].values == (20.5, -4.25, -40.0)
    att = samples(items, "attitude")
    assert att[0].values == (0.6614378, 0.5, 0.25, 0.5)  # x, y, z, w(, accuracy) -> w, x, y, z
    assert att[1].values == (math.sqrt(1 - 0.25 - 0.0625 - 0.25), 0.5, 0.25, 0.5)  # w from x, y, z
    assert samples(items, "phone_gravity")[0].values == (0.0, 0.5, 9.75)
    assert samples(items, "user_acc")[0].values == (0.125, -0.75, 0.0)
    assert not any(isinstance(x, DeviceEvent) for x in items)
    assert dev.health()["accuracy"]["ss/mag"] == 2
    assert dev.codec.stats.errors == 0


def test_single_sensor_path_has_no_type():
    dev = device(types="gyroscope")
    items = run(dev, [sensorserver_event((0.5, 0.25, 0.125), T0), sensorserver_event((0.5, 0.25, 0.125), T0 + 10**7)])
    g = samples(items, "gyro")
    assert [s.t_device_ns for s in g] == [T0, T0 + 10**7] and g[1].values == (0.5, 0.25, 0.125)


def test_touchscreen_device():
    dev = device(types="touchscreen")
    assert [(s.name, s.kind, s.clock, s.nominal_rate_hz) for s in dev.streams] == [("ss/touch", "touch", None, None)]
    items = run(dev, [sensorserver_touch("ACTION_DOWN", 120.5, 300.0), sensorserver_touch("ACTION_MOVE", 121.0, 310.0),
                      sensorserver_touch("ACTION_UP", 121.0, 310.0)])
    assert [s.values for s in samples(items, "touch")] == [(0.0, 120.5, 300.0), (1.0, 121.0, 310.0),
                                                          (2.0, 121.0, 310.0)]


def test_unexpected_types_and_touches_are_counted_not_errors(caplog):
    dev = device()
    items = run(dev, [sensorserver_event((1.0, 2.0, 3.0), T0, 3, "android.sensor.light")] * 3
                + [sensorserver_touch("ACTION_DOWN", 1.0, 2.0)])
    assert samples(items) == []
    assert dev.health()["unexpected"] == {"android.sensor.light": 3, "touch": 1}
    assert dev.codec.stats.errors == 0
    assert caplog.text.count("did not ask for") == 1


def test_unusable_events_are_counted_errors():
    dev = device()
    items = run(dev, [sensorserver_event((1.0, 2.0), T0, 3, ACC),  # too few values for an accelerometer
                      sensorserver_event((1.0, 2.0, 3.0), T0),      # no type on a multi-sensor connection
                      sensorserver_event((1.0, 2.0, 3.0), T0, 3, ACC)])
    assert dev.codec.stats.framing_errors == 2 == dev.health()["bad_events"]
    assert len(samples(items, "acc")) == 1
    assert any(isinstance(x, DeviceEvent) and x.kind is EventKind.PROTOCOL_ERRORS for x in items)
    with pytest.raises(ProtocolError, match="2 value"):
        run(device(strict=True), [sensorserver_event((1.0, 2.0), T0, 3, ACC)])


BAD_MESSAGES = {
    "not JSON": b"{values:[1,2,3]}",
    "not UTF-8": b'{"values":[1,2,3],"timestamp":1,"accuracy":3}\xff',
    "an array": b"[1,2,3]",
    "NaN": b'{"values":[NaN,2,3],"timestamp":1,"accuracy":3}',
    "infinite": b'{"values":[1e400,2,3],"timestamp":1,"accuracy":3}',
    "no timestamp": b'{"values":[1,2,3],"accuracy":3}',
    "no accuracy": b'{"values":[1,2,3],"timestamp":1}',
    "float timestamp": b'{"values":[1,2,3],"timestamp":1.5,"accuracy":3}',
    "bool timestamp": b'{"values":[1,2,3],"timestamp":true,"accuracy":3}',
    "negative timestamp": b'{"values":[1,2,3],"timestamp":-1,"accuracy":3}',
    "huge timestamp": b'{"values":[1,2,3],"timestamp":99999999999999999999,"accuracy":3}',
    "string value": b'{"values":[1,"2",3],"timestamp":1,"accuracy":3}',
    "empty values": b'{"values":[],"timestamp":1,"accuracy":3}',
    "too many values": json.dumps({"values": [0.0] * 65, "timestamp": 1, "accuracy": 3}).encode(),
    "type not a string": b'{"values":[1,2,3],"timestamp":1,"accuracy":3,"type":5}',
    "GPS message": b'{"longitude":11.5,"latitude":48.1,"altitude":500,"time":1700000000000}',
    "bad touch action": b'{"action":"ACTION_CANCEL","x":1,"y":2}',
    "touch without y": b'{"action":"ACTION_UP","x":1}',
    "deep nesting": b"[" * 100000 + b"]" * 100000,
    "oversized": b'{"values":[' + b"1," * SS_MAX_BYTES + b'1],"timestamp":1,"accuracy":3}',
}


@pytest.mark.parametrize("name", BAD_MESSAGES)
def test_malformed_messages_are_counted_not_raised(name):
    dev = device(types="accelerometer")
    items = run(dev, [BAD_MESSAGES[name], sensorserver_event((1.0, 2.0, 3.0), T0)])
    assert dev.codec.stats.framing_errors == 1
    assert len(samples(items, "acc")) == 1
    with pytest.raises(ProtocolError):
        SensorServerCodec(strict=True).feed(BAD_MESSAGES[name])


@settings(max_examples=300, deadline=None)
@given(st.one_of(st.binary(max_size=300),
                 st.recursive(st.none() | st.booleans() | st.integers() | st.floats(allow_nan=False)
                              | st.text(max_size=8),
                              lambda c: st.lists(c, max_size=5) | st.dictionaries(
                                  st.sampled_from(["values", "timestamp", "accuracy", "type", "action", "x", "y"]), c,
                                  max_size=7), max_leaves=20).map(lambda o: json.dumps(o).encode())))
def test_fuzzed_input_is_counted_and_never_raises(data):
    dev = device(types="accelerometer,gyroscope")
    run(dev, [data])
    c = dev.codec.stats
    assert c.framing_errors == (1 - c.frames) + dev.health()["bad_events"]


# -- round trip and replay ------------------------------------------------------------------------
def test_codec_round_trip():
    c = SensorServerCodec()
    frames = [SensorServerEvent(ACC, (0.1, -9.81, 1e-7), T0, 3), SensorServerEvent(None, (1.0,), 0, -1),
              SensorServerEvent("com.vendor.sensor.x", tuple(float(i) for i in range(16)), 2**62, 0),
              SensorServerTouch("ACTION_MOVE", 10.5, 20.25)]
    for f in frames:
        assert c.feed(c.encode(f)) == [f]
    with pytest.raises(ValueError):
        c.encode(SensorServerEvent(ACC, (math.nan, 0.0, 0.0), T0, 3))


def test_refeeding_the_same_chunks_gives_identical_samples():
    msgs = []
    for i in range(200):
        t = T0 + i * 5_000_000
        msgs.append(sensorserver_event((0.01 * i, -0.5, 9.8), t, 3, ACC))
        msgs.append(sensorserver_event((0.1, 0.02 * i, -0.3), t + 1_000_000, 3, GYRO))
    msgs[17] = b"garbage"
    chunks = [Chunk(m, 10**12 + i * 2_500_000 + (i * 7919) % 3_000_000, Direction.RX) for i, m in enumerate(msgs)]
    runs = []
    for _ in range(2):
        dev = device(rate=200)
        runs.append(repr([x for c in chunks for x in dev.process_chunk(c)]))
    assert runs[0] == runs[1] and "ss/gyro" in runs[0]
