"""The SensorServer codec: the Android app's JSON text frames in, sensor events and touches out.

This module owns the SensorServer message syntax: bytes in, typed frames out, bad input counted.
What the values mean (streams, units, clock) is ``devices.phone_apps.sensorserver``; the app's
connection (its WebSocket paths and close codes) is ``devices.transports.sensorserver``.

``SensorServerCodec`` (name ``sensorserver``): one ``feed(data)`` is one WebSocket
text frame. A sensor event ``{"values":[...],"timestamp":ns,"accuracy":int}`` (plus ``"type"`` on
the multi-sensor path) becomes a ``SensorServerEvent``. A touch ``{"action":"ACTION_DOWN|
ACTION_MOVE|ACTION_UP","x":px,"y":px}`` becomes a ``SensorServerTouch``. Anything else (not
UTF-8, not JSON, a non-finite number, wrong types, too many values, a GPS message) is a counted
framing error.

The codec keeps its state in itself, so the same chunks always give the same frames. ``encode``
is the inverse of ``feed``, used by simulators and round-trip tests.
"""

from __future__ import annotations

import json
import math
from typing import Any, NamedTuple

from devices.codecs.base import BadMessageError, MessageCodec

#: Bounds of one SensorServer message.
SS_MAX_BYTES = 65536
SS_MAX_VALUES = 64
SS_MAX_TYPE = 128
SS_TOUCH_ACTIONS = ("ACTION_DOWN", "ACTION_MOVE", "ACTION_UP")
_MAX_NS = 1 << 62  # device times stay within int64 (devices.base.MAX_DEVICE_NS)

_Reject = BadMessageError  # why an input is rejected


class SensorServerEvent(NamedTuple):
    """One Android sensor event: ``type`` (``Sensor.getStringType()``, ``None`` on the single-sensor
    path), values, ``SensorEvent.timestamp`` (ns since boot) and accuracy."""

    type: str | None
    values: tuple[float, ...]
    timestamp: int
    accuracy: int


class SensorServerTouch(NamedTuple):
    """One touch from ``/touchscreen``: ``ACTION_DOWN``, ``ACTION_MOVE`` or ``ACTION_UP`` at x, y (px)."""

    action: str
    x: float
    y: float


SensorServerFrame = SensorServerEvent | SensorServerTouch


def _reject_constant(name: str) -> float:
    raise _Reject(f"non-finite number {name}")


def _ss_num(v: Any, what: str) -> float:
    if type(v) is int:
        if v.bit_length() > 1023:
            raise _Reject(f"{what} is an integer of {v.bit_length()} bits, beyond a float's range")
        return float(v)
    if type(v) is float and math.isfinite(v):
        return v
    raise _Reject(f"{what} is not a finite number ({type(v).__name__})")


def _ss_int(v: Any, what: str, lo: int, hi: int) -> int:
    if type(v) is not int:
        raise _Reject(f"{what} is not an integer ({type(v).__name__})")
    if not lo <= v <= hi:
        raise _Reject(f"{what}={v} out of range [{lo}, {hi}]")
    return v


class SensorServerCodec(MessageCodec):
    """SensorServer JSON text frames (one per ``feed``); see the module docstring."""

    name = "sensorserver"

    max_bytes = SS_MAX_BYTES

    def parse(self, data: bytes) -> list[SensorServerFrame]:
        try:
            obj = json.loads(data.decode("utf-8"), parse_constant=_reject_constant)
        except UnicodeDecodeError as exc:
            raise _Reject(f"not UTF-8 ({exc.reason} at byte {exc.start})") from None
        except _Reject:
            raise
        except (ValueError, RecursionError) as exc:
            raise _Reject(f"not JSON ({exc})") from None
        if not isinstance(obj, dict):
            raise _Reject(f"message is a JSON {type(obj).__name__}, not an object")
        return [self._touch(obj) if "action" in obj else self._event(obj)]

    @staticmethod
    def _event(obj: dict[str, Any]) -> SensorServerEvent:
        for key in ("values", "timestamp", "accuracy"):
            if key not in obj:
                raise _Reject(f'no "{key}": neither a sensor event nor a touch')
        vals = obj["values"]
        if not isinstance(vals, list) or not 1 <= len(vals) <= SS_MAX_VALUES:
            raise _Reject(f'"values" is not an array of 1 to {SS_MAX_VALUES} numbers')
        values = tuple(_ss_num(v, f"values[{i}]") for i, v in enumerate(vals))
        ts = _ss_int(obj["timestamp"], "timestamp", 0, _MAX_NS)
        acc = _ss_int(obj["accuracy"], "accuracy", -(1 << 31), (1 << 31) - 1)
        typ = obj.get("type")
        if typ is not None and (type(typ) is not str or not 0 < len(typ) <= SS_MAX_TYPE):
            raise _Reject(f'"type" is not a sensor type name of 1 to {SS_MAX_TYPE} characters')
        return SensorServerEvent(typ, values, ts, acc)

    @staticmethod
    def _touch(obj: dict[str, Any]) -> SensorServerTouch:
        action = obj["action"]
        if action not in SS_TOUCH_ACTIONS:
            raise _Reject(f"touch action {str(action)[:40]!r} is not one of {'|'.join(SS_TOUCH_ACTIONS)}")
        if "x" not in obj or "y" not in obj:
            raise _Reject("touch without x and y")
        return SensorServerTouch(action, _ss_num(obj["x"], "x"), _ss_num(obj["y"], "y"))

    def reject(self, message: str, raw: bytes = b"") -> None:
        """Count an event the device layer found unusable (too few values for its sensor, an
        unexpected type) as a framing error.

        Raises:
            ProtocolError: only in strict mode.
        """
        self._bad("framing", message, 0, raw[:200])

    def encode(self, frame: SensorServerFrame) -> bytes:
        """The JSON text the app sends for ``frame``.

        Raises:
            TypeError: not a SensorServer frame.
            ValueError: a non-finite value.
        """
        if isinstance(frame, SensorServerEvent):
            d: dict[str, Any] = {"values": list(frame.values), "timestamp": frame.timestamp,
                                 "accuracy": frame.accuracy}
            if frame.type is not None:
                d["type"] = frame.type
        elif isinstance(frame, SensorServerTouch):
            d = {"action": frame.action, "x": frame.x, "y": frame.y}
        else:
            raise TypeError(f"not a SensorServer frame: {type(frame).__name__}")
        return json.dumps(d, separators=(",", ":"), allow_nan=False).encode("utf-8")


__all__ = ["SS_MAX_BYTES", "SS_MAX_TYPE", "SS_MAX_VALUES", "SS_TOUCH_ACTIONS", "SensorServerCodec",
           "SensorServerEvent", "SensorServerFrame", "SensorServerTouch"]
