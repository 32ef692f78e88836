"""OSC phones (``OscCodec``, ``OscPhone``): ZIG SIM and GyrOSC-style address maps and custom maps.

There are no real recordings of ZIG SIM or GyrOSC in ``../shared/traces``, so every input here is
built from the documented layouts (``docs/design/phone-protocols.md`` section 1) with python-osc's
own ``osc_message_builder`` / ``osc_bundle_builder``: real library bytes, float32 arguments as the
apps send them. Values are chosen exact in float32 so decoded values can be compared exactly.
"""

from __future__ import annotations

import logging
import math
import struct
import time

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from pythonosc.osc_bundle_builder import IMMEDIATELY, OscBundleBuilder
from pythonosc.osc_message_builder import OscMessageBuilder

from capture.errors import ConfigError, ProtocolError
from capture.sample import Chunk, DeviceEvent, Direction, EventKind, Sample
from devices.codecs.osc import OSC_IMMEDIATELY, OSC_MAX_DEPTH, OscCodec, OscFrame, OscMsg
from devices.phone_apps.base import G0
from devices.phone_apps.osc import OscPhone, zigsim_uuid
from devices.transports import open_transport
from sim_devices.phone_apps_sim import gyrosc_bundle, osc_bundle, osc_message, zigsim_bundle

UUID = "my-phone_1"


def device(strict: bool = False, **opts) -> OscPhone:
    return OscPhone("zs", open_transport("loop://"), opts, strict=strict)


def feed(dev: OscPhone, datagrams: list[bytes], t0: int = 10**9, period: int = 16_666_667) -> list:
    out = []
    for i, d in enumerate(datagrams):
        out += dev.process_chunk(Chunk(d, t0 + i * period, Direction.RX))
    return out


def samples(items, stream: str | None = None) -> list[Sample]:
    return [x for x in items if isinstance(x, Sample) and (stream is None or x.stream.endswith("/" + stream))]


def message(address: str, *args) -> OscMessageBuilder:
    b = OscMessageBuilder(address=address)
    for a in args:
        b.add_arg(a)
    return b


def zigsim_snapshot(uuid: str = UUID, prefix: str = "", timestamp=IMMEDIATELY) -> bytes:
    """One ZIG SIM tick as the app builds it (ServiceManager.getOSC): a bundle of /<uuid>/<cmd> messages."""
    b = OscBundleBuilder(timestamp)
    p = f"{prefix}/{uuid}"
    for addr, args in ((f"{p}/deviceinfo", ("iPhone 15", uuid, "ios", "17.4", 1179, 2556)),
                       (f"{p}/accel", (0.125, -0.25, 0.5)),       # user acceleration, g
                       (f"{p}/gravity", (0.0, -0.5, -0.75)),      # g
                       (f"{p}/gyro", (0.5, -1.5, 2.25)),          # rad/s
                       (f"{p}/quaternion", (0.125, 0.25, 0.5, 0.75)),  # x, y, z, w
                       (f"{p}/touch01", (0.5,)), (f"{p}/touch02", (-0.25,)),
                       (f"{p}/touchradius0", (12.0,)), (f"{p}/touchforce0", (0.75,)),
                       (f"{p}/touch11", (-1.0,)), (f"{p}/touch12", (1.0,)),
                       (f"{p}/compass", (271.5, 1))):              # not mapped
        b.add_content(message(addr, *args).build())
    return b.build().dgram


# -- ZIG SIM ------------------------------------------------------------------------------------
def test_zigsim_streams_are_declared_before_any_byte():
    dev = device()
    assert [(s.name, s.kind, s.nominal_rate_hz, s.clock) for s in dev.streams] == [
        ("zs/imu", "imu", 60.0, None), ("zs/user_acc", "acc", 60.0, None), ("zs/phone_gravity", "acc", 60.0, None),
        ("zs/attitude", "quat", 60.0, None), ("zs/touch", "touch", None, None)]
    assert dev.streams[0].channels == ("ax", "ay", "az", "gx", "gy", "gz")
    assert dev.streams[3].channels == ("w", "x", "y", "z")
    assert not any(s.name.endswith(("/orientation", "/gravity", "/linear_acc")) for s in dev.streams)


@pytest.mark.parametrize("platform, sign", [("ios", -1.0), ("android", 1.0)])
@pytest.mark.parametrize("prefix", ["", "/ZIGSIM"])
def test_zigsim_snapshot_decodes_to_exact_values(platform, sign, prefix):
    dev = device(platform=platform)
    items = feed(dev, [zigsim_snapshot(prefix=prefix)])
    (imu,) = samples(items, "imu")
    # accel is user acceleration: the accelerometer reads (accel + gravity), in g
    assert imu.values == (sign * 0.125 * G0 + sign * 0.0 * G0, sign * -0.25 * G0 + sign * -0.5 * G0,
                          sign * 0.5 * G0 + sign * -0.75 * G0, 0.5, -1.5, 2.25)
    assert imu.values[2] == pytest.approx(sign * -0.25 * G0)
    assert samples(items, "user_acc")[0].values == (sign * 0.125 * G0, sign * -0.25 * G0, sign * 0.5 * G0)
    assert samples(items, "phone_gravity")[0].values == (sign * 0.0 * G0, sign * -0.5 * G0, sign * -0.75 * G0)
    assert samples(items, "attitude")[0].values == (0.75, 0.125, 0.25, 0.5)  # x, y, z, w -> w, x, y, z
    touch = samples(items, "touch")
    assert [s.values[:3] for s in touch] == [(0.0, 0.5, -0.25), (1.0, -1.0, 1.0)]
    assert touch[0].values[3:] == (12.0, 0.75)
    assert all(math.isnan(v) for v in touch[1].values[3:])  # slot 1 sent no radius or force
    assert all(s.t_device_ns is None for s in samples(items))
    h = dev.health()
    assert h["info"] == {"name": "iPhone 15", "uuid": UUID, "os": "ios", "osversion": "17.4", "width": "1179",
                         "height": "2556"}
    assert h["uuid"] == UUID
    assert h["unmatched"] == {f"{prefix}/{UUID}/compass": 1}
    assert h["framing_errors"] == 0 and h["snapshots"] == 1


def test_flat_phone_reads_plus_g_on_z_with_the_default_ios_sign():
    """CoreMotion lying flat, screen up: gravity (0, 0, -1) g; perfcap's convention reads +9.81 on z."""
    items = feed(device(), [zigsim_bundle(UUID, accel=(0.0, 0.0, 0.0), gravity=(0.0, 0.0, -1.0),
                                          gyro=(0.0, 0.0, 0.0))])
    assert samples(items, "imu")[0].values[2] == G0
    assert samples(items, "phone_gravity")[0].values[2] == G0


def test_partial_snapshots_leave_missing_channels_nan():
    items = feed(device(), [zigsim_bundle(UUID, gyro=(0.5, 0.25, 1.0)),
                            zigsim_bundle(UUID, accel=(0.5, 0.0, 0.0), gravity=(0.0, 0.0, -1.0)),
                            zigsim_bundle(UUID, accel=(0.5, 0.0, 0.0))])
    imu = samples(items, "imu")
    assert len(imu) == 2  # the third snapshot has no gravity and no gyro: no imu reading
    assert all(math.isnan(v) for v in imu[0].values[:3]) and imu[0].values[3:] == (0.5, 0.25, 1.0)
    assert imu[1].values[:3] == (-0.5 * G0, -0.0, G0) and all(math.isnan(v) for v in imu[1].values[3:])
    assert len(samples(items, "user_acc")) == 2 and len(samples(items, "phone_gravity")) == 1


def test_held_repeats_are_still_recorded():
    snap = zigsim_snapshot()
    items = feed(OscPhone("zs", open_transport("loop://"), {}), [snap] * 4)
    imu = samples(items, "imu")
    assert [s.seq for s in imu] == [0, 1, 2, 3]
    assert len({s.values for s in imu}) == 1
    assert [s.t_bus_ns for s in imu] == sorted(s.t_bus_ns for s in imu)


def test_an_address_repeated_in_one_datagram_starts_a_new_snapshot():
    b = OscBundleBuilder(IMMEDIATELY)
    for v in (0.5, 0.25):
        b.add_content(message(f"/{UUID}/gyro", v, 0.0, 0.0).build())
    items = feed(device(), [b.build().dgram])
    assert [s.values[3] for s in samples(items, "imu")] == [0.5, 0.25]


def test_uuid_option_accepts_only_that_device():
    dev = device(uuid=UUID)
    items = feed(dev, [zigsim_snapshot("other-phone"), zigsim_snapshot(UUID, "/ZIGSIM")])
    assert len(samples(items, "imu")) == 1
    assert dev.health()["foreign_uuids"] == {"other-phone": 12}
    assert dev.codec.stats.errors == 0


def test_the_uuid_of_a_datagram_for_routing():
    c = OscCodec()
    assert zigsim_uuid(c.feed(zigsim_snapshot(UUID, "/ZIGSIM"))[0]) == UUID
    assert zigsim_uuid(c.feed(zigsim_snapshot("other"))[0]) == "other"
    assert zigsim_uuid(c.feed(gyrosc_bundle({"rrate": (0.0, 0.0, 0.0)}, prefix="/gyrosc/phone1"))[0]) is None
    assert zigsim_uuid(c.feed(osc_message("/gyrosc/rrate", 0.0))[0]) == "gyrosc"  # any /a/b is ZIG SIM-shaped


def test_nested_bundles_and_a_future_timetag_do_not_block(monkeypatch):
    """python-osc's Dispatcher sleeps until a future time tag; the codec must never wait."""
    def no_sleep(_s: float) -> None:
        raise AssertionError("the OSC codec slept")

    monkeypatch.setattr(time, "sleep", no_sleep)
    future = time.time() + 7 * 86400
    inner = OscBundleBuilder(future)
    inner.add_content(message(f"/{UUID}/gyro", 0.5, 0.25, 0.125).build())
    middle = OscBundleBuilder(future)
    middle.add_content(message(f"/{UUID}/accel", 0.0, 0.0, 0.0).build())
    middle.add_content(inner.build())
    outer = OscBundleBuilder(future + 1.0)
    outer.add_content(message(f"/{UUID}/gravity", 0.0, 0.0, -1.0).build())
    outer.add_content(middle.build())
    dgram = outer.build().dgram
    (frame,) = OscCodec().feed(dgram)
    assert [m.address for m in frame.messages] == [f"/{UUID}/gravity", f"/{UUID}/accel", f"/{UUID}/gyro"]
    ntp_now = (time.time() + 2208988800) * 2**32
    assert frame.timetag is not None and frame.timetag > ntp_now + 86400 * 2**32  # reported, not waited for
    items = feed(device(), [dgram])  # time.sleep raises: the device does not wait for the time tag either
    assert samples(items, "imu")[0].values == (0.0, 0.0, G0, 0.5, 0.25, 0.125)


# -- GyrOSC ---------------------------------------------------------------------------------------
def test_gyrosc_preset():
    dev = device(map="gyrosc")
    assert [(s.name, s.kind) for s in dev.streams] == [("zs/imu", "imu"), ("zs/phone_gravity", "acc"),
                                                       ("zs/attitude", "quat"), ("zs/euler", "euler")]
    items = feed(dev, [gyrosc_bundle({"gyro": (0.5, -0.25, 1.0), "rrate": (0.125, 0.25, -0.5),
                                      "accel": (0.0, 0.25, -1.0), "grav": (0.0, 0.0, -1.0),
                                      "quat": (0.75, 0.125, 0.25, 0.5), "amp": (0.5,)})])
    assert samples(items, "imu")[0].values == (-0.0 * G0, -0.25 * G0, G0, 0.125, 0.25, -0.5)
    assert samples(items, "phone_gravity")[0].values == (-0.0, -0.0, G0)
    assert samples(items, "attitude")[0].values == (0.75, 0.125, 0.25, 0.5)
    assert samples(items, "euler")[0].values == (math.degrees(0.5), math.degrees(-0.25), math.degrees(1.0))
    assert dev.health()["unmatched"] == {"/gyrosc/amp": 1}


def test_gyrosc_prefix_units_and_quaternion_order():
    dev = device(map="gyrosc", prefix="/gyrosc/phone1/", accel_unit="m/s^2", platform="android", quat_order="xyzw")
    items = feed(dev, [gyrosc_bundle({"accel": (0.5, 0.25, 9.75), "quat": (0.125, 0.25, 0.5, 0.75)},
                                     prefix="/gyrosc/phone1"),
                       gyrosc_bundle({"accel": (1.0, 1.0, 1.0)})])  # the default prefix is not this phone's
    assert [s.values[:3] for s in samples(items, "imu")] == [(0.5, 0.25, 9.75)]
    assert samples(items, "attitude")[0].values == (0.75, 0.125, 0.25, 0.5)
    assert dev.health()["unmatched"] == {"/gyrosc/accel": 1}


# -- custom maps ----------------------------------------------------------------------------------
def test_custom_map_builds_streams_and_scales():
    dev = device(map="/acc:imu:ax,ay,az:9.80665; /gyro:imu:gx,gy,gz ;/knob:extra_ctl:_,level:0.5;/pad:touch:x,y")
    assert [(s.name, s.kind, s.channels, s.units, s.nominal_rate_hz) for s in dev.streams] == [
        ("zs/imu", "imu", ("ax", "ay", "az", "gx", "gy", "gz"), ("m/s^2",) * 3 + ("rad/s",) * 3, 60.0),
        ("zs/extra_ctl", "extra", ("level",), ("1",), 60.0),
        ("zs/touch", "touch", ("x", "y"), ("1", "1"), None)]
    items = feed(dev, [osc_bundle([("/acc", [0.5, 0.25, 1.0]), ("/gyro", [1.0, 2.0, 3.0]), ("/knob", ["k", 0.5]),
                                   ("/pad", [0.25, 0.75])]),
                       osc_message("/gyro", 0.5, 0.5, 0.5)])
    imu = samples(items, "imu")
    assert imu[0].values == (0.5 * 9.80665, 0.25 * 9.80665, 9.80665, 1.0, 2.0, 3.0)
    assert all(math.isnan(v) for v in imu[1].values[:3]) and imu[1].values[3:] == (0.5, 0.5, 0.5)
    assert samples(items, "extra_ctl")[0].values == (0.25,)
    assert samples(items, "touch")[0].values == (0.25, 0.75)


@pytest.mark.parametrize("bad", [
    "/acc:imu", "/acc:imu:ax,ay,az:9.8:extra", "acc:imu:ax,ay,az", "/acc:Imu:ax", "/acc:orientation:x,y,z",
    "/acc:gravity:x,y,z", "/acc:linear_acc:x", "/acc:imu:x,y,z", "/q:attitude:a,b,c,d", "/acc:acc:x,y,z:abc",
    "/acc:acc:x,y,z:0", "/acc:acc:x,y,z:inf", "/acc:acc:_,_", "/acc:acc:x;/acc:acc:y", "/a:acc:x;/b:acc:x",
    "/a b:acc:x", "/acc:acc:1x", " ; ;", "/acc:acc:x,,y",
])
def test_bad_custom_maps_are_config_errors_naming_the_form(bad):
    with pytest.raises(ConfigError, match=r"expected map=zigsim, map=gyrosc, or map=ADDRESS:STREAM:CHANNELS|fed by"):
        device(map=bad)


@pytest.mark.parametrize("opts, what", [
    ({"map": "gyrosc", "uuid": "x"}, "uuid"), ({"prefix": "/p"}, "prefix"), ({"quat_order": "xyzw"}, "quat_order"),
    ({"map": "/a:acc:x", "platform": "android"}, "platform"), ({"map": "gyrosc", "quat_order": "wxyy"}, "quat_order"),
    ({"map": "gyrosc", "prefix": "gyrosc"}, "prefix"), ({"uuid": "bad uuid!"}, "uuid"), ({"rate": -1}, "rate"),
    ({"platform": "windows"}, "platform"),
])
def test_options_are_checked(opts, what):
    with pytest.raises(ConfigError, match=what):
        device(**opts)


def test_unmatched_addresses_are_counted_and_logged_once(caplog):
    dev = device(map="/acc:acc:x,y,z")
    with caplog.at_level(logging.INFO, logger="devices.phone_apps.osc"):
        feed(dev, [osc_bundle([("/mystery", [1.0]), ("/acc", [0.0, 0.0, 1.0]), ("/other", ["s"])])] * 5)
    assert dev.health()["unmatched"] == {"/mystery": 5, "/other": 5}
    logged = [r.getMessage() for r in caplog.records if "not in map" in r.getMessage()]
    assert len(logged) == 2 and "/mystery" in logged[0] and "/other" in logged[1]


# -- bad input ------------------------------------------------------------------------------------
def test_wrong_arguments_are_counted_framing_errors():
    dev = device()
    items = feed(dev, [osc_bundle([(f"/{UUID}/gyro", [0.5, 0.25]), (f"/{UUID}/accel", ["x", 0.0, 0.0]),
                                   (f"/{UUID}/gravity", [True, 0.0, 0.0]),
                                   (f"/{UUID}/quaternion", [0.0, 0.0, 0.0, 1.0])])])
    assert dev.codec.stats.framing_errors == 3 and dev.health()["bad_args"] == 3
    assert [s.stream for s in samples(items)] == ["zs/attitude"]
    assert any(isinstance(x, DeviceEvent) and x.kind is EventKind.PROTOCOL_ERRORS for x in items)
    with pytest.raises(ProtocolError, match="gyro needs 3"):
        feed(device(strict=True), [osc_message(f"/{UUID}/gyro", 0.5)])


def _negative_size() -> bytes:
    return b"#bundle\x00" + struct.pack(">Q", 1) + struct.pack(">i", -4) + b"\x00" * 4


def _nested(depth: int) -> bytes:
    b = message("/deep", 1.0).build()
    for _ in range(depth):
        bb = OscBundleBuilder(IMMEDIATELY)
        bb.add_content(b)
        b = bb.build()
    return b.dgram


BAD_DATAGRAMS = {
    "empty": b"",
    "text": b"hello world\n",
    "truncated bundle": zigsim_snapshot()[:30],
    "negative element size (python-osc loops forever on it)": _negative_size(),
    "element size past the end": b"#bundle\x00" + struct.pack(">Q", 1) + struct.pack(">i", 400) + b"/a\x00\x00",
    "element size not a multiple of 4":
        b"#bundle\x00" + struct.pack(">Q", 1) + struct.pack(">i", 5) + b"/a\x00\x00,\x00",
    "element neither message nor bundle": b"#bundle\x00" + struct.pack(">Q", 1) + struct.pack(">i", 4) + b"xxxx",
    "unsupported type tag": b"/a\x00\x00,c\x00\x00\x00\x00\x00a",
    "type tags without comma": b"/a\x00\x00ff\x00\x00\x00\x00\x00\x00",
    "truncated float": b"/a\x00\x00,f\x00\x00\x3f",
    "unterminated address": b"/abc",
    "too deep": _nested(OSC_MAX_DEPTH + 1),
    "oversized": b"/a\x00\x00" + b"\x00" * 70000,
    "non-UTF-8 address": b"/\xff\xfe\x00,\x00\x00\x00",
}


@pytest.mark.parametrize("name", BAD_DATAGRAMS)
def test_malformed_datagrams_are_counted_not_raised(name):
    dev = device()
    items = feed(dev, [BAD_DATAGRAMS[name], zigsim_snapshot()])
    assert dev.codec.stats.framing_errors == 1
    assert len(samples(items, "imu")) == 1  # the next datagram is fine
    with pytest.raises(ProtocolError):
        OscCodec(strict=True).feed(BAD_DATAGRAMS[name])


def test_nesting_up_to_the_limit_is_accepted():
    (frame,) = OscCodec().feed(_nested(OSC_MAX_DEPTH))
    assert frame.messages == (OscMsg("/deep", (1.0,)),)


@settings(max_examples=300, deadline=None)
@given(st.binary(max_size=400))
def test_garbage_is_counted_and_never_raises(data):
    dev = device()
    feed(dev, [data, b"#bundle\x00" + data, b"/" + data])
    c = dev.codec.stats
    assert c.framing_errors == (3 - c.frames) + dev.health()["bad_args"]


@settings(max_examples=300, deadline=None)
@given(st.data())
def test_corrupted_snapshots_are_counted_and_never_raise(data):
    good = bytearray(zigsim_snapshot())
    for _ in range(data.draw(st.integers(1, 6))):
        good[data.draw(st.integers(0, len(good) - 1))] = data.draw(st.integers(0, 255))
    cut = data.draw(st.integers(0, len(good)))
    dev = device()
    feed(dev, [bytes(good[:cut]), bytes(good)])
    c = dev.codec.stats
    # every datagram is a frame or a dropped datagram; mapped messages with bad arguments add errors
    assert c.framing_errors == (2 - c.frames) + dev.health()["bad_args"]


# -- codec round trip and replay ------------------------------------------------------------------
def test_codec_round_trip():
    c = OscCodec()
    frames = [
        OscFrame((OscMsg("/a/b", (0.5, -3, "text", True, False, None, b"\x01\x02", (1, (2.5, "x")))),), None),
        OscFrame((OscMsg("/x", ()), OscMsg("/y", (1.25,)), OscMsg("/z", (2**40,))), OSC_IMMEDIATELY),
        OscFrame((OscMsg("/t", (0.125,)),), 0xDEADBEEF_12345678),
        OscFrame((), 42),
    ]
    for f in frames:
        assert c.feed(c.encode(f)) == [f]
    assert c.encode(OscMsg("/m", (1.0,))) == osc_message("/m", 1.0)
    assert c.stats.errors == 0
    # floats go out as float32, as the apps send them
    (back,) = c.feed(c.encode(OscMsg("/f", (0.1,))))
    assert back.messages[0].args[0] == struct.unpack(">f", struct.pack(">f", 0.1))[0]


def test_refeeding_the_same_chunks_gives_identical_samples():
    chunks = []
    for i in range(120):
        v = (0.01 * i, -0.5, 0.25)
        d = zigsim_bundle(UUID, accel=v, gravity=(0.0, 0.0, -1.0), gyro=(0.1 * i, 0.0, -0.1),
                          quaternion=(0.0, 0.0, 0.0, 1.0), touches=[(0.5, 0.5)] if i % 7 else [])
        jitter = (i * 7919) % 5_000_000
        chunks.append(Chunk(d if i % 13 else b"garbage", 10**9 + i * 16_666_667 + jitter, Direction.RX))
    runs = []
    for _ in range(2):
        dev = device()
        runs.append(repr([x for c in chunks for x in dev.process_chunk(c)]))
    assert runs[0] == runs[1]
    assert "zs/imu" in runs[0] and "zs/touch" in runs[0]
