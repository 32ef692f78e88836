"""Phones running the SensorServer app (Android), whose WebSocket server perfcap connects to (kind ``sensorserver``).

This module owns what SensorServer's values mean: streams, units and the clock. The message syntax
is ``devices.codecs.sensorserver``; the connection (paths, close codes) is
``devices.transports.sensorserver``. The app is not in ``../shared/traces``; the layout follows
``docs/design/phone-protocols.md`` (section 2).

``SensorServerPhone`` (kind ``sensorserver``): perfcap is the WebSocket client of the app, and one
chunk is one text frame (``SensorServerCodec``). Option ``types`` (default
``accelerometer,gyroscope``; short or ``android.sensor.*`` names) sets the streams.
accelerometer becomes ``acc`` (m/s^2, with gravity), gyroscope ``gyro``, magnetic_field ``mag``,
rotation_vector ``attitude`` (w, x, y, z; w computed when the phone sends only x, y, z), gravity
``phone_gravity``, linear_acceleration ``user_acc``. ``touchscreen``, alone, is the app's touch
connection: ``touch`` (phase 0 down, 1 move, 2 up; x, y px; no timestamp, so irregular). The
device clock is ``SensorEvent.timestamp`` (ns since boot, tick_hz 1e9), one clock for all sensor
streams. ``rate`` (default 0, unknown: Android takes the requested rate as a hint) is their
nominal rate. ``SensorServerPhone.ws_path(types)`` builds the app's WebSocket path, and
``CLOSE_CODES`` explains its close codes 4001-4009.
"""

from __future__ import annotations

import logging
from typing import TYPE_CHECKING, Any, ClassVar

from capture.clock import MONOTONIC, Clock
from capture.errors import ConfigError
from capture.sample import DeviceClockSpec, StreamInfo
from devices.base import Reading
from devices.codecs.sensorserver import SensorServerCodec, SensorServerEvent, SensorServerTouch
from devices.options import Option
from devices.phone_apps.base import (
    ACC_CHANNELS,
    ACC_UNITS,
    GYRO_CHANNELS,
    GYRO_UNITS,
    MAG_CHANNELS,
    QUAT_CHANNELS,
    AppDevice,
    NameTally,
    StreamDecl,
    quat_from_vector,
)
from devices.transports.sensorserver import SENSORSERVER_CLOSE_CODES, sensorserver_path

if TYPE_CHECKING:
    from collections.abc import Iterable, Mapping

    from devices.transports.base import Transport

log = logging.getLogger(__name__)

#: SensorServer's clock: ``SensorEvent.timestamp``, ns since boot (``elapsedRealtimeNanos`` base).
SENSORSERVER_CLOCK = DeviceClockSpec(tick_hz=1e9)
#: Sensor types a SensorServerPhone maps: short Android name -> (stream declaration, values needed).
SENSORSERVER_TYPES: dict[str, tuple[StreamDecl, int]] = {
    "accelerometer": (StreamDecl("acc", "acc", ACC_CHANNELS, ACC_UNITS), 3),
    "gyroscope": (StreamDecl("gyro", "gyro", GYRO_CHANNELS, GYRO_UNITS), 3),
    "magnetic_field": (StreamDecl("mag", "mag", MAG_CHANNELS, ("uT",) * 3), 3),
    "rotation_vector": (StreamDecl("attitude", "quat", QUAT_CHANNELS, ("1",) * 4,
                              "Android rotation vector: phone frame relative to east-north-up"), 3),
    "gravity": (StreamDecl("phone_gravity", "acc", ACC_CHANNELS, ACC_UNITS), 3),
    "linear_acceleration": (StreamDecl("user_acc", "acc", ACC_CHANNELS, ACC_UNITS), 3),
}
SENSORSERVER_TOUCH = StreamDecl("touch", "touch", ("phase", "x", "y"), ("1", "px", "px"),
                           "screen pixels from the top left (SensorServer's touch view)", regular=False)
_TOUCH_PHASE = {"ACTION_DOWN": 0.0, "ACTION_MOVE": 1.0, "ACTION_UP": 2.0}
_ANDROID = "android.sensor."


def parse_sensorserver_types(text: str | Iterable[str], where: str = "sensorserver") -> list[str]:
    """Short type names from ``types`` (comma list or names; ``android.sensor.`` prefix optional).

    Raises:
        ConfigError: none, an unknown or repeated type, or touchscreen mixed with sensors.
    """
    items = text.split(",") if isinstance(text, str) else list(text)
    out: list[str] = []
    form = "types=TYPE,TYPE,... of " + ", ".join(SENSORSERVER_TYPES) + ", or types=touchscreen alone"
    for raw in items:
        t = str(raw).strip().lower()
        if not t:
            continue
        t = t.removeprefix(_ANDROID)
        if t != "touchscreen" and t not in SENSORSERVER_TYPES:
            raise ConfigError(f"{where}: unknown sensor type {str(raw).strip()!r}; expected {form}", source=where)
        if t in out:
            raise ConfigError(f"{where}: sensor type {t} is listed twice", source=where)
        out.append(t)
    if not out:
        raise ConfigError(f"{where}: no sensor type; expected {form}", source=where)
    if "touchscreen" in out and len(out) > 1:
        raise ConfigError(f"{where}: touchscreen is a connection of its own (the app's /touchscreen path); give it to"
                          f" a separate device; expected {form}", source=where)
    return out


class SensorServerPhone(AppDevice[SensorServerCodec]):
    """A phone running the SensorServer app (Android); perfcap connects to its WebSocket server."""

    kind = "sensorserver"
    description = "SensorServer app (Android): perfcap is the WebSocket client of the phone"
    codec_cls = SensorServerCodec
    options: ClassVar[dict[str, Option]] = {
        "types": Option(str, "accelerometer,gyroscope",
                        "sensor types (" + ", ".join(SENSORSERVER_TYPES) + "), or touchscreen alone"),
        "rate": Option(float, 0.0, "nominal rate of the sensor streams, Hz (0 = unknown; the app's sampling "
                       "period is only a hint to Android)", min=0.0, max=10_000.0),
    }
    #: The app's WebSocket close codes and what they mean (shown to the user by the transport).
    CLOSE_CODES: ClassVar[dict[int, str]] = SENSORSERVER_CLOSE_CODES

    def __init__(self, name: str, transport: Transport, options: Mapping[str, Any] | None = None,
                 clock: Clock = MONOTONIC, strict: bool = False) -> None:
        super().__init__(name, transport, options, clock, strict)
        #: last accuracy (Android SENSOR_STATUS_*) per stream
        self.accuracy: dict[str, int] = {}
        self.unexpected = NameTally()
        #: decoded events the streams cannot take (too few values, no type where one is needed)
        self.bad_events = 0

    @classmethod
    def ws_path(cls, types: str | Iterable[str]) -> str:
        """The app's WebSocket path for ``types``: ``/sensor/connect?type=android.sensor.X`` for one,
        ``/sensors/connect?types=<URL-encoded JSON array>`` for two or more, ``/touchscreen`` for touches.

        Raises:
            ConfigError: an unknown or repeated type, or none.
        """
        return sensorserver_path(parse_sensorserver_types(types))

    @staticmethod
    def close_reason(code: int | None) -> str:
        """What a WebSocket close code from the app means (a generic text for other codes)."""
        if code is None:
            return "connection lost"
        return SENSORSERVER_CLOSE_CODES.get(code, f"closed with code {code}")

    @property
    def path(self) -> str:
        """This device's WebSocket path."""
        return sensorserver_path(self.types)

    def declare_streams(self) -> list[StreamInfo]:
        self.types = parse_sensorserver_types(str(self.opts["types"]), f"device {self.name} (sensorserver)")
        if self.types == ["touchscreen"]:
            decls = [SENSORSERVER_TOUCH]
            self._need: dict[str, tuple[int, int]] = {}
        else:
            decls = [SENSORSERVER_TYPES[t][0] for t in self.types]
            self._need = {t: (i, SENSORSERVER_TYPES[t][1]) for i, t in enumerate(self.types)}
        self._touch = 0 if self.types == ["touchscreen"] else None
        return self._declare(decls, self.opts["rate"] or None, SENSORSERVER_CLOCK)

    def frame_to_readings(self, frame: SensorServerEvent | SensorServerTouch) -> Iterable[Reading]:
        if isinstance(frame, SensorServerTouch):
            if self._touch is None:
                self._unexpected("touch", "a touch on a sensor connection")
                return []
            return [Reading(self._touch, (_TOUCH_PHASE[frame.action], frame.x, frame.y))]
        if frame.type is None:
            if len(self._need) != 1:
                self.bad_events += 1
                self.codec.reject("sensor event without \"type\" on a multi-sensor connection; dropped")
                return []
            t = next(iter(self._need))
        else:
            t = frame.type.lower()
            t = t.removeprefix(_ANDROID)
        spec = self._need.get(t)
        if spec is None:
            self._unexpected(frame.type or "?", "a sensor type this device did not ask for")
            return []
        si, need = spec
        v = frame.values
        if len(v) < need:
            self.bad_events += 1
            self.codec.reject(f"{t} event with {len(v)} value(s), {need} needed; dropped")
            return []
        self.accuracy[self.streams[si].name] = frame.accuracy
        vals: tuple[float, ...]
        if t == "rotation_vector":
            vals = (v[3], v[0], v[1], v[2]) if len(v) >= 4 else quat_from_vector(v[0], v[1], v[2])
        else:
            vals = v[:3]
        return [Reading(si, vals, frame.timestamp)]

    def _unexpected(self, what: str, why: str) -> None:
        if self.unexpected.add(what[:128]):
            log.warning("sensorserver %s: %s (%s); dropped (counted in health()['unexpected'])",
                        self.name, why, what[:128])

    def health(self) -> dict[str, Any]:
        """Base counters plus ``accuracy`` (last per stream), ``unexpected`` (events of types not
        asked for, per type) and ``bad_events`` (events counted as framing errors by the device)."""
        h = super().health()
        h.update(accuracy=dict(self.accuracy), unexpected=dict(self.unexpected.counts), bad_events=self.bad_events)
        return h


__all__ = ["SENSORSERVER_CLOCK", "SENSORSERVER_TOUCH", "SENSORSERVER_TYPES", "SensorServerPhone",
           "parse_sensorserver_types"]
