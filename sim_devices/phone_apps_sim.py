"""Message builders for the phone apps of ``devices.phone_apps``: ZIG SIM and GyrOSC-style OSC
datagrams, HyperIMU rows and SensorServer text frames, as the apps send them.

Pure functions, no networking: tests and simulators feed what they return to a transport or
straight to a device. OSC is built with python-osc's own builders (float32 arguments, as the apps
send them). The layouts follow ``docs/design/phone-protocols.md``; there are no recordings of these
apps to copy from.
"""

from __future__ import annotations

import json
from collections.abc import Iterable, Mapping, Sequence
from typing import Any

from pythonosc.osc_bundle_builder import IMMEDIATELY, OscBundleBuilder
from pythonosc.osc_message_builder import OscMessageBuilder

from devices.codecs.hyperimu import HyperImuCodec
from devices.codecs.osc import OSC_IMMEDIATELY
from devices.codecs.sensorserver import SensorServerCodec, SensorServerEvent, SensorServerTouch
from devices.codecs.textline import TextFrame

Vec = Sequence[float]


def _lists(v: Any) -> Any:
    return [_lists(x) for x in v] if isinstance(v, (tuple, list)) else v


def osc_message(address: str, *args: object) -> bytes:
    """One OSC message datagram (floats as float32)."""
    b = OscMessageBuilder(address=address)
    for a in args:
        b.add_arg(_lists(a))
    return bytes(b.build().dgram)


def osc_bundle(messages: Iterable[tuple[str, Sequence[object]]], timetag: int = OSC_IMMEDIATELY) -> bytes:
    """A bundle of ``(address, args)`` messages with a raw NTP time tag (1: immediately)."""
    b = OscBundleBuilder(IMMEDIATELY)
    for address, args in messages:
        m = OscMessageBuilder(address=address)
        for a in args:
            m.add_arg(_lists(a))
        b.add_content(m.build())
    dgram = bytearray(b.build().dgram)
    dgram[8:16] = int(timetag).to_bytes(8, "big")
    return bytes(dgram)


def zigsim_messages(uuid: str, *, accel: Vec | None = None, gravity: Vec | None = None, gyro: Vec | None = None,
                    quaternion: Vec | None = None, touches: Sequence[Sequence[float]] = (),
                    deviceinfo: Sequence[object] | None = None, zigsim_prefix: bool = False
                    ) -> list[tuple[str, Sequence[object]]]:
    """The messages of one ZIG SIM snapshot, in the app's order.

    Args:
        uuid: the app's device UUID.
        accel: user acceleration x, y, z in g (CoreMotion, gravity removed).
        gravity: gravity x, y, z in g.
        gyro: rotation rate x, y, z in rad/s.
        quaternion: attitude x, y, z, w.
        touches: per slot (x, y) or (x, y, radius, force).
        deviceinfo: name, uuid, os, os version, width, height.
        zigsim_prefix: lead the addresses with ``/ZIGSIM``.
    """
    p = f"/ZIGSIM/{uuid}" if zigsim_prefix else f"/{uuid}"
    out: list[tuple[str, Sequence[object]]] = []
    if deviceinfo is not None:
        out.append((f"{p}/deviceinfo", list(deviceinfo)))
    for name, v in (("accel", accel), ("gravity", gravity), ("gyro", gyro), ("quaternion", quaternion)):
        if v is not None:
            out.append((f"{p}/{name}", [float(x) for x in v]))
    for i, t in enumerate(touches):
        out.append((f"{p}/touch{i}1", [float(t[0])]))
        out.append((f"{p}/touch{i}2", [float(t[1])]))
        if len(t) > 2:
            out.append((f"{p}/touchradius{i}", [float(t[2])]))
            out.append((f"{p}/touchforce{i}", [float(t[3])]))
    return out


def zigsim_bundle(uuid: str, timetag: int = OSC_IMMEDIATELY, **snapshot: Any) -> bytes:
    """One ZIG SIM datagram: a bundle of ``zigsim_messages(uuid, **snapshot)``."""
    return osc_bundle(zigsim_messages(uuid, **snapshot), timetag)


def gyrosc_bundle(values: Mapping[str, Vec], prefix: str = "/gyrosc", timetag: int = OSC_IMMEDIATELY) -> bytes:
    """One GyrOSC-style bundle: ``{"rrate": (x, y, z), "accel": ..., "quat": ..., "gyro": ...}``."""
    return osc_bundle([(f"{prefix}/{k}", [float(x) for x in v]) for k, v in values.items()], timetag)


def hyperimu_rows(rows: Sequence[Sequence[float]], *, sensors: Sequence[str] = ("accelerometer", "gyroscope",
                  "magnetometer"), timestamps: Sequence[int] | None = None, mac: str | None = None,
                  gps: Sequence[Vec] | None = None, end: bytes = b"\r\n") -> bytes:
    """HyperIMU rows: sensor values per row (3 per sensor, in order), optional epoch-ms timestamps,
    MAC address and GPS (lat, lon, alt) per row, each row ended by ``end`` (``\\r\\n`` or ``#``).

    Raises:
        ValueError: a row of the wrong length, or a bad row end.
    """
    codec = HyperImuCodec(sensors=sensors, timestamp=timestamps is not None, mac=mac is not None,
                          gps=gps is not None)
    out = []
    for k, r in enumerate(rows):
        vals: list[float] = [] if timestamps is None else [float(timestamps[k])]
        vals += [float(x) for x in r]
        if gps is not None:
            vals += [float(x) for x in gps[k]]
        out.append(codec.encode(TextFrame(tuple(vals), (1 << len(vals)) - 1), mac=mac or "", end=end))
    return b"".join(out)


def sensorserver_event(values: Sequence[float], timestamp_ns: int, accuracy: int = 3,
                       sensor_type: str | None = None) -> bytes:
    """One SensorServer sensor event text frame (``type`` as on the multi-sensor path, e.g.
    ``android.sensor.accelerometer``)."""
    return SensorServerCodec().encode(SensorServerEvent(sensor_type, tuple(float(v) for v in values), timestamp_ns,
                                                        accuracy))


def sensorserver_touch(action: str, x: float, y: float) -> bytes:
    """One SensorServer touch text frame (``ACTION_DOWN``, ``ACTION_MOVE`` or ``ACTION_UP``)."""
    return SensorServerCodec().encode(SensorServerTouch(action, float(x), float(y)))


def sensorserver_raw(obj: Mapping[str, object]) -> bytes:
    """Any JSON object as a text frame (for malformed-input tests)."""
    return json.dumps(obj).encode()


__all__ = ["gyrosc_bundle", "hyperimu_rows", "osc_bundle", "osc_message", "sensorserver_event", "sensorserver_raw",
           "sensorserver_touch", "zigsim_bundle", "zigsim_messages"]
